"""Regenerate the pictures of ``docs/stats.md`` (``docs/img/stats-*.png``, ``view-frame*.png``, ``view-house.png``).

It synthesizes one house, generates a small dataset from it and draws every picture with the real ``mpchair``
commands, so the pictures show what a user gets. The JSON output of each command is saved in the work folder, and
the numbers quoted in ``docs/stats.md`` are printed at the end.

Usage: ``python tools/doc_pictures.py [--out-dir docs/img] [--work out/doc-pictures]``. Same seeds, same pictures.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The console script installed next to this interpreter: the venv's mpchair, not whatever is first on PATH.
MPCHAIR = Path(sys.executable).with_name("mpchair")
KITTI = "tests/data/kitti"  # the 6 vendored real KITTI frames, relative to ROOT (docs/stats.md quotes this path)
# The example frame's chairs should all be visible in the picture, not only in the dense label grid.
MIN_SCAN_POINTS = 100


class CommandError(RuntimeError):
    pass


def run(args: list[str], cwd: Path) -> str:
    """Run one mpchair command, echo it (to stderr, so stdout stays the summary) and return its stdout."""
    shown = " ".join(shlex.quote(a) for a in ["mpchair", *args])
    print(f"$ (cd {cwd}) {shown}", file=sys.stderr)
    proc = subprocess.run([str(MPCHAIR), *args], cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise CommandError(f"{shown} failed (exit {proc.returncode}):\n{proc.stderr.strip()}")
    return proc.stdout


def run_json(args: list[str], cwd: Path, save: Path) -> dict:
    out = run([*args, "--json"], cwd)
    save.write_text(out)
    return json.loads(out)


def pick_frame(manifest: dict) -> str:
    """The frame with the most kept chairs, all of them with at least MIN_SCAN_POINTS scan points (ties: the one
    whose least-seen chair has the most points, then the lowest id). Needs at least 2 chairs, so the picture shows
    several boxes.

    ``scan_points`` (points of the stored scan inside the box) is used rather than ``points_in_box``, which counts
    the pixels of the dense label grid: a box can pass the generator's filters and still hold only a few scan
    points, and such a box looks empty in the picture.
    """
    best: tuple[int, int, str] | None = None
    for f in manifest["frames"]:
        points = [k["scan_points"] for k in f["kept"]]
        if len(points) < 2 or min(points) < MIN_SCAN_POINTS:
            continue
        key = (len(points), min(points), f["frame"])
        if best is None or key[:2] > best[:2]:  # strict: equal counts keep the earlier (lower) frame id
            best = key
    if best is None:
        raise CommandError(f"no frame has >= 2 kept chairs with >= {MIN_SCAN_POINTS} scan points each; "
                           "use more --frames or pass --frame")  # fmt: skip
    return best[2]


def density_line(name: str, d: dict) -> str:
    return (f"{name}: {d['count']} frames, D min {d['min']:.5f}  median {d['median']:.5f}  mean {d['mean']:.5f}  "
            f"max {d['max']:.5f}  std {d['std']:.5f}")  # fmt: skip


def boxes_lines(b: dict) -> list[str]:
    lines = [f"boxes per frame: {b['boxes_per_frame']['mean']:.2f} mean, {b['frames']} frames"]
    for name, c in b["classes"].items():
        lines += [
            f"{name}: {c['count']} boxes",
            f"  size: l {c['l']['mean']:.3f} ± {c['l']['std']:.3f}, w {c['w']['mean']:.3f} ± {c['w']['std']:.3f}, "
            f"h {c['h']['mean']:.3f} ± {c['h']['std']:.3f} m",
            f"  points per box: min {c['points']['min']:g}, median {c['points']['median']:g}, "
            f"mean {c['points']['mean']:.1f}, max {c['points']['max']:g}",
            f"  distance: {c['distance']['min']:.2f}–{c['distance']['max']:.2f} m, "
            f"median {c['distance']['median']:.2f} m",
        ]
    rejected = b.get("rejected")
    if rejected:
        lines.append("rejected: " + ", ".join(f"{k} {v}" for k, v in rejected.items()))
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out-dir", type=Path, default=ROOT / "docs" / "img", help="where the PNGs go (default docs/img)")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "doc-pictures",
                   help="work folder (default out/doc-pictures): houses/ and dataset/, both rebuilt on every run, "
                        "and the commands' JSON output")  # fmt: skip
    p.add_argument("--house-seed", type=int, default=1, help="mpchair synth --seed (default 1)")
    p.add_argument("--dataset-seed", type=int, default=0, help="mpchair generate --seed (default 0)")
    p.add_argument("--frames", type=int, default=48, help="frames to generate (default 48)")
    p.add_argument("--workers", type=int, default=2, help="generate workers (default 2; the bytes do not depend on it)")
    p.add_argument("--frame", help="frame for view-frame*.png (default: picked from manifest.json, see pick_frame)")
    args = p.parse_args(argv)
    if not MPCHAIR.exists():
        print(f"error: {MPCHAIR} not found; run this with the venv's python (pip install -e .)", file=sys.stderr)
        return 2

    work = args.work.resolve()
    out_dir = args.out_dir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    # generate resumes a dataset folder that already exists; starting afresh makes the pictures depend on the
    # seeds and options only, not on what an earlier run with other options left behind.
    for sub in ("houses", "dataset"):
        shutil.rmtree(work / sub, ignore_errors=True)
    # Commands on the synthetic data run inside `work` with relative paths, because the figures' titles show the
    # dataset path as given: an absolute (temporary) path would change the pictures from one machine to the next.
    try:
        synth = json.loads(run(["synth", "--out", "houses", "--houses", "1", "--seed", str(args.house_seed),
                                "--json"], work))  # fmt: skip
        house = synth["houses"][0]
        gen = run_json(["generate", "--root", "houses", "--house", house, "--frames", str(args.frames), "--out",
                        "dataset", "--seed", str(args.dataset_seed), "--workers", str(args.workers), "--quiet"],
                       work, work / "generate.json")  # fmt: skip

        config = str(ROOT / "configs" / "models" / "mpchair_dense.yaml")
        density = run_json(
            ["stats", "--density", "dataset", "--config", config, "--plot", str(out_dir / "stats-density.png")],
            work,
            work / "stats-density.json",
        )
        # The same invocation as the KITTI table in docs/stats.md (`--preset kitti` equals kitti_car_*.yaml, and
        # the vendored scans are already FOV-cropped, so `--fov-crop` would change nothing; both are tested).
        kitti = run_json(
            ["stats", "--density", KITTI, "--preset", "kitti", "--plot", str(out_dir / "stats-density-kitti.png")],
            ROOT,
            work / "stats-density-kitti.json",
        )
        boxes = run_json(["stats", "--boxes", "dataset", "--plot", str(out_dir / "stats-boxes.png")],
                         work, work / "stats-boxes.json")  # fmt: skip

        manifest = json.loads((work / "dataset" / "manifest.json").read_text())
        frame = args.frame if args.frame is not None else pick_frame(manifest)
        # No --zmax: the default ceiling cut (2 m above the floor), as a user gets it.
        view = run_json(["view", "dataset", "--frame", frame, "--out", str(out_dir / "view-frame.png"), "--3d",
                         "--size", "1000", "800"], work, work / "view-frame.json")  # fmt: skip
        # Two levels side by side: a wide canvas, or the square default leaves half the picture blank.
        house_view = run_json(["view-house", "--root", "houses", "--house", house, "--dataset", "dataset",
                               "--out", str(out_dir / "view-house.png"), "--size", "1600", "860"],
                              work, work / "view-house.json")  # fmt: skip
    except (CommandError, json.JSONDecodeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1

    kept = next(f for f in manifest["frames"] if f["frame"] == view["frame"])["kept"]
    lines = [
        f"house {house} (synth --seed {args.house_seed}), {gen['frames']} frames (generate --seed "
        f"{args.dataset_seed}): {gen['kept']} kept boxes, rejected {gen['rejected']}",
        density_line("mpchair density (512 x 768)", density),
        density_line("KITTI density (440 x 504)", kitti),
        *boxes_lines(boxes),
        f"view frame {view['frame']}: {view['points']} points, {view['boxes']} boxes, scan points per chair "
        f"{[k['scan_points'] for k in kept]}",
        f"view-house: {house_view['faces']} faces, {house_view['objects']} chairs, "
        f"{house_view['viewpoints']} viewpoints",
        f"pictures in {out_dir}, JSON in {work}",
    ]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
