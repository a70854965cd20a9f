"""Benchmark ``mpchair generate`` (``mp3d-depth90``) on a reference synthetic house; prints ratios, asserts nothing.

Reports, in one run:

* pipeline throughput: frames/s of ``generate`` with ``--workers`` (default 2) into a temporary folder;
* raw Embree time for the same number of rays: the scan pattern cast (embreex scene, one thread, no Python work
  around it) from the generated frames' own poses, repeated until it reaches the rays the pipeline cast
  (scan + dense visibility rays, as counted in the frame records);
* the ratio ``pipeline CPU-seconds / raw raycast seconds``, with pipeline CPU-seconds = wall time x workers (an
  upper bound on the CPU the pipeline used);
* the same ratio against the pipeline's *own* rays: the frames are generated once more in one process with every
  Embree call recorded (viewpoint checks, dense visibility, silhouettes, scans), and exactly those calls are replayed
  and timed alone (``pipeline_cpu_over_replay``, the issue's measure: the whole command, start-up included);
  ``pipeline_cpu_over_parallel_replay`` replays them split over ``--workers`` processes at once instead, i.e. the
  raycasts alone with the pipeline's parallelism (wall over wall);
  ``frames_cpu_over_replay`` is the same for the frame loop alone (``startup_and_manifest_s`` is the rest: reading
  and hashing the house, loading the compiled kernels, writing the manifest: fixed costs that 1,000 frames amortise);
* image_2 timings (``image_2_ms``): the compiled depth projection and the ISA-L PNG encoder against their plain
  versions (numpy; Pillow at its fastest level) on the benchmark's own frames.

Usage: ``python tools/bench_generate.py [--frames 1000] [--workers 2] [--seed 0] [--subdivide 0] [--workdir DIR]
[--json]``
(``--subdivide 3`` gives the house a real Matterport3D face count at the same geometry).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def _keep(x):
    """A copy of an engine-call argument; a shared origin (a stride-0 view, see ``raycast._ray_origins``) is kept as
    its one row and expanded again by :func:`_expand` (1,000 frames of dense rays would otherwise need gigabytes)."""
    import numpy as np

    if x.ndim == 2 and x.strides[0] == 0:
        return ("shared", np.array(x[:1], copy=True), len(x))
    return np.array(x, copy=True)


def _expand(x):
    from mpchair.scan.raycast import _ray_origins  # the pipeline's own stride-0 origin view

    if isinstance(x, tuple):
        _, row, n = x
        return _ray_origins(row, n)
    return x


def _record_engine_calls(run) -> list[tuple]:
    """Run ``run()`` with every Embree scene call recorded: ``[(scene, args, kwargs)]`` with copies of the arrays."""

    from mpchair.scan import raycast

    calls: list[tuple] = []
    original = raycast.EmbreeRaycaster.__init__

    class Recorder:
        def __init__(self, scene):
            self.scene = scene

        def run(self, *a, **kw):
            calls.append((self.scene, tuple(_keep(x) for x in a), kw))
            return self.scene.run(*a, **kw)

    def init(self, *a, **kw):
        original(self, *a, **kw)
        self._scene = Recorder(self._scene)

    raycast.EmbreeRaycaster.__init__ = init
    try:
        run()
    finally:
        raycast.EmbreeRaycaster.__init__ = original
    return calls


def _parallel_replay(calls: list[tuple], workers: int) -> float:
    """Wall seconds to replay the recorded calls split over ``workers`` forked processes (every ``workers``-th call
    each), i.e. the same rays raycast with the pipeline's parallelism: two Embree processes on two cores run slower
    per ray than one alone (shared caches), and the pipeline's CPU-seconds include that."""
    import multiprocessing

    def run(k: int) -> None:
        for scene, a, kw in calls[k::workers]:
            scene.run(*a, **kw)

    ctx = multiprocessing.get_context("fork")  # children inherit the recorded calls and the committed scenes
    procs = [ctx.Process(target=run, args=(k,)) for k in range(workers)]
    t = time.perf_counter()
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join()
    return time.perf_counter() - t


def _time_image_2(dataset: Path, sensor) -> dict[str, float]:
    """ms per frame of the image_2 steps against their plain versions, on the benchmark's own frames (same run)."""
    import io
    import time

    from PIL import Image

    from mpchair.dataset.image import depth_image, depth_image_reference, png_bytes
    from mpchair.kitti import read_velodyne
    from mpchair.scan.sensors import camera_calib

    calib, size = camera_calib(sensor.camera), (sensor.camera.width, sensor.camera.height)
    scans = [read_velodyne(p) for p in sorted((dataset / "training" / "velodyne").glob("*.bin"))[:50]]
    images = [depth_image(s, calib, size, sensor.max_range) for s in scans]

    def pillow(img):
        buf = io.BytesIO()
        Image.fromarray(img, mode="L").save(buf, format="PNG", compress_level=1)
        return buf.getvalue()

    out = {}
    for name, fn, inputs in [
        ("depth_image", lambda s: depth_image(s, calib, size, sensor.max_range), scans),
        ("depth_image_numpy", lambda s: depth_image_reference(s, calib, size, sensor.max_range), scans),
        ("png_isal", png_bytes, images),
        ("png_pillow_level1", pillow, images),
    ]:
        t = time.perf_counter()
        for x in inputs:
            fn(x)
        out[name] = round((time.perf_counter() - t) / len(inputs) * 1e3, 3)
    return out


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    from mpchair.dataset.generate import GenerateRequest, generate
    from mpchair.matterport.house import read_house
    from mpchair.matterport.source import find_houses
    from mpchair.scan.raycast import EmbreeRaycaster
    from mpchair.scan.sensors import load_sensor, scan_directions
    from mpchair.synth import subdivide_house, synthesize_house, write_house

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="seed of the reference house and of the dataset")
    p.add_argument("--subdivide", type=int, default=0,
                   help="split every triangle into 4 this many times (3-4: real Matterport3D face counts)")
    p.add_argument("--workdir", type=Path, default=None,
                   help="where the benchmark's houses and datasets are written (default: the system temp folder; "
                        "a tmpfs such as /dev/shm leaves the disk out of the timing)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)

    from mpchair.core.heap import keep_freed_memory

    keep_freed_memory()  # as `mpchair generate` does (its workers do it too)
    with tempfile.TemporaryDirectory(prefix="mpchair-bench-", dir=args.workdir) as tmp:
        tmp = Path(tmp)
        house = subdivide_house(synthesize_house(args.seed, levels=1), args.subdivide)
        write_house(tmp / "houses", house)
        t0 = time.perf_counter()
        summary = generate(GenerateRequest(root=tmp / "houses", houses=(house.id,), frames=args.frames,
                                           out=tmp / "ds", seed=args.seed, workers=args.workers, progress=False))
        wall = time.perf_counter() - t0
        frames_s = summary.made / summary.frames_per_second  # the frame loop alone (no start-up, no manifest)
        records = json.loads((tmp / "ds" / "manifest.json").read_text())["frames"]
        rays = int(sum(r["rays"] for r in records))
        h = read_house(find_houses(tmp / "houses")[house.id])
        rc = EmbreeRaycaster(h.vertices, h.faces)
        d = scan_directions(load_sensor("mp3d-depth90"))
        poses = [np.vstack([np.array(r["pose"]), [0, 0, 0, 1]]) for r in records]
        batches = []
        left, k = rays, 0
        while left > 0:  # precompute float32 inputs so that only Embree is timed
            T = poses[k % len(poses)]
            n = min(left, len(d))
            o32 = np.empty((n, 3), dtype=np.float32)
            o32[:] = (T[:3, 3] - rc.centre).astype(np.float32)
            batches.append((o32, np.ascontiguousarray(d[:n] @ T[:3, :3].T, dtype=np.float32)))
            left -= n
            k += 1
        t1 = time.perf_counter()
        for o32, d32 in batches:
            rc._scene.run(o32, d32)  # the raw engine call (what EmbreeRaycaster.cast wraps)
        raw = time.perf_counter() - t1
        # The same frames again in one process, recording every engine call (viewpoint checks, dense visibility,
        # silhouettes, scans: the rays the pipeline really casts), then replaying exactly those calls, timed alone.
        calls = _record_engine_calls(lambda: generate(GenerateRequest(
            root=tmp / "houses", houses=(house.id,), frames=args.frames, out=tmp / "ds_rec", seed=args.seed,
            workers=1, progress=False)))
        calls = [(scene, tuple(_expand(x) for x in a), kw) for scene, a, kw in calls]
        t2 = time.perf_counter()
        for scene, a, kw in calls:
            scene.run(*a, **kw)
        replay = time.perf_counter() - t2
        replay_rays = int(sum(len(a[1]) for _, a, _ in calls))
        parallel = _parallel_replay(calls, args.workers)
        image_ms = _time_image_2(tmp / "ds", load_sensor("mp3d-depth90"))
    result = {
        "house": house.id, "faces": len(house.faces), "frames": args.frames, "workers": args.workers,
        "wall_s": round(wall, 3), "frames_per_s": round(args.frames / wall, 2), "rays": rays,
        "rays_per_frame": round(rays / args.frames), "raw_embree_s": round(raw, 3),
        "raw_embree_mrays_per_s": round(rays / raw / 1e6, 2),
        "pipeline_cpu_over_raw": round(wall * args.workers / raw, 2),
        "replayed_rays": replay_rays, "replayed_rays_per_frame": round(replay_rays / args.frames),
        "replay_embree_s": round(replay, 3), "replay_mrays_per_s": round(replay_rays / replay / 1e6, 2),
        "parallel_replay_wall_s": round(parallel, 3),
        "pipeline_cpu_over_parallel_replay": round(wall / parallel, 2),
        "pipeline_cpu_over_replay": round(wall * args.workers / replay, 2),
        "startup_and_manifest_s": round(wall - frames_s, 3),
        "frames_cpu_over_replay": round(frames_s * args.workers / replay, 2), "kept_boxes": summary.kept,
        "image_2_ms": image_ms,
        "workdir": str(args.workdir or tempfile.gettempdir()),
        "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key:>24}: {value}")
        print(f"targets: frames/s >= 25 ({result['frames_per_s']}), pipeline / raw raycast of its own rays <= 1.5 "
              f"({result['pipeline_cpu_over_replay']}; against scan-pattern rays: {result['pipeline_cpu_over_raw']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
