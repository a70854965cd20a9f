"""Regenerate the pictures and the numbers of ``docs/stats.md`` (``docs/img/stats-*.png``, ``view-frame*.png``,
``view-house.png``, and the text between its ``<!-- doc_pictures.py NAME: begin/end -->`` markers).

It synthesizes one house, generates a small dataset from it and draws every picture with the real ``mpchair``
commands, so the pictures show what a user gets; eight more houses give the multi-house box sizes. The JSON output
of each command is saved in the work folder, and the numbers ``docs/stats.md`` quotes are written into it between
its markers (nothing outside them changes). ``--check`` makes only the numbers (no pictures) and exits 1 when the
doc's blocks differ from them; ``tests/test_doc_numbers.py`` runs it, so a stale number fails the tests.

Usage: ``python tools/doc_pictures.py [--out-dir docs/img] [--work out/doc-pictures] [--doc docs/stats.md]
[--check]`` (the front-end of this module). Same seeds, same pictures and numbers.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from detector.config import CONFIG_DIR
from mpchair.core.atomic import write_text
from mpchair.core.clitools import run_script
from mpchair.core.doctable import replace_block
from mpchair.core.errors import InputError, RunError
from mpchair.paper import KITTI_DENSITY
from mpchair.paper import MATTERPORT_CHAIR_DENSITY as MC
from reproduction.checkout import ROOT, require_checkout

# The console script installed next to this interpreter: the venv's mpchair, not whatever is first on PATH.
MPCHAIR = Path(sys.executable).with_name("mpchair")
KITTI = "tests/data/kitti"  # the 6 vendored real KITTI frames, relative to ROOT (docs/stats.md quotes this path)
# The example frame's chairs should all be visible in the picture, not only in the dense label grid.
MIN_SCAN_POINTS = 100
# The multi-house comparison of docs/stats.md: houses (synth --seed 0) and frames per house.
MULTI_HOUSES, MULTI_FRAMES = 8, 30
#: The paper's KITTI D (section IV, test split), which the doc compares against: median and min–max range.
PAPER_KITTI_MEDIAN, PAPER_KITTI_RANGE = KITTI_DENSITY.median, (KITTI_DENSITY.min, KITTI_DENSITY.max)


class CommandError(RunError):
    """An ``mpchair`` command that failed, a doc whose markers do not match the script's blocks, or (``--check``) a
    doc whose numbers are stale: one ``error:`` line (with a failed command's stderr), exit 1."""


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


def markers(name: str) -> tuple[str, str]:
    """The comment lines around block ``name`` in the doc (invisible once rendered)."""
    return f"<!-- doc_pictures.py {name}: begin -->", f"<!-- doc_pictures.py {name}: end -->"


def fill_blocks(text: str, blocks: dict[str, str], doc: Path) -> str:
    """``text`` with the lines between each block's markers replaced by ``blocks[name]``; a missing marker is an
    error (the doc and the script must name the same blocks)."""
    for name, body in blocks.items():
        try:
            text = replace_block(text, *markers(name), body, doc)
        except InputError as e:
            raise CommandError(str(e)) from None
    return text


def measure(work: Path, args: argparse.Namespace, plots: Path | None) -> dict:
    """Run the commands whose numbers docs/stats.md quotes (with ``--plot`` into ``plots`` unless None); their JSON,
    also saved as ``work/measured.json``."""
    def plot(name: str) -> list[str]:
        return [] if plots is None else ["--plot", str(plots / name)]

    synth = json.loads(run(["synth", "--out", "houses", "--houses", "1", "--seed", str(args.house_seed),
                            "--json"], work))  # fmt: skip
    house = synth["houses"][0]
    gen = run_json(["generate", "--root", "houses", "--house", house, "--frames", str(args.frames), "--out",
                    "dataset", "--seed", str(args.dataset_seed), "--workers", str(args.workers), "--quiet"],
                   work, work / "generate.json")  # fmt: skip
    config = str(CONFIG_DIR / "mpchair_dense.yaml")
    density = run_json(["stats", "--density", "dataset", "--config", config, *plot("stats-density.png")], work,
                       work / "stats-density.json")  # fmt: skip
    # The same invocation as the KITTI table in docs/stats.md (`--preset kitti` equals kitti_car_*.yaml, and
    # the vendored scans are already FOV-cropped, so `--fov-crop` would change nothing; both are tested).
    kitti = run_json(["stats", "--density", KITTI, "--preset", "kitti", *plot("stats-density-kitti.png")], ROOT,
                     work / "stats-density-kitti.json")  # fmt: skip
    boxes = run_json(["stats", "--boxes", "dataset", *plot("stats-boxes.png")], work, work / "stats-boxes.json")
    manifest = json.loads((work / "dataset" / "manifest.json").read_text())
    frame = args.frame if args.frame is not None else pick_frame(manifest)

    many = json.loads(run(["synth", "--out", "houses8", "--houses", str(MULTI_HOUSES), "--seed", "0", "--json"],
                          work))["houses"]  # fmt: skip
    run(["generate", "--root", "houses8", *sum((["--house", h] for h in many), []), "--frames", str(MULTI_FRAMES),
         "--out", "dataset8", "--seed", "0", "--workers", str(args.workers), "--quiet"], work)  # fmt: skip
    boxes8 = run_json(["stats", "--boxes", "dataset8"], work, work / "stats-boxes8.json")
    measured = {"house": house, "generate": gen, "density": density, "kitti": kitti, "boxes": boxes,
                "manifest": manifest, "frame": frame, "boxes8": boxes8}  # fmt: skip
    (work / "measured.json").write_text(json.dumps(measured))  # everything number_blocks reads
    return measured


def number_blocks(m: dict, args: argparse.Namespace) -> dict[str, str]:
    """The text of every marked block of docs/stats.md, from the commands' JSON (:func:`measure`)."""
    kitti = m["kitti"]
    W, H = kitti["geometry"]["grid"]
    rw, rh = kitti["geometry"]["real_grid"]
    real = [f["pillars"] / (rw * rh) for f in kitti["frames"]]
    rows = [f"| {f['id']} | {f['points']} | {f['points_in_range']} | {f['pillars']} | {f['density']:.5f} | {r:.5f} |"
            for f, r in zip(kitti["frames"], real)]
    real_sorted = sorted(real)
    n = len(real_sorted)
    real_median = (real_sorted[(n - 1) // 2] + real_sorted[n // 2]) / 2
    below = 100 * (PAPER_KITTI_MEDIAN - kitti["median"]) / PAPER_KITTI_MEDIAN
    inside = sum(PAPER_KITTI_RANGE[0] <= f["density"] <= PAPER_KITTI_RANGE[1] for f in kitti["frames"])
    kitti_block = "\n".join([
        f"| frame | points | in range | non-empty pillars | *D* ({W} × {H}, used) | *D* ({rw} × {rh}) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        "| | min | median | mean | max |",
        "|---|---|---|---|---|",
        f"| **paper, KITTI test** | {PAPER_KITTI_RANGE[0]} | **{PAPER_KITTI_MEDIAN}** | – | {PAPER_KITTI_RANGE[1]} |",
        f"| these {n} frames, FOV-cropped, {W} × {H} | {kitti['min']:.5f} | **{kitti['median']:.5f}** | "
        f"{kitti['mean']:.5f} | {kitti['max']:.5f} |",
        f"| same frames, {rw} × {rh} | {min(real):.5f} | {real_median:.5f} | {sum(real) / n:.5f} | {max(real):.5f} |",
        "",
        f"On the padded grid {f'all {n}' if inside == n else f'{inside} of the {n}'} cropped frames fall inside "
        "the paper's min–max range, and their median is",
        f"{below:.0f}% below the paper's.",
    ])

    d, house = m["density"], m["house"]
    dW, dH = d["geometry"]["grid"]
    density_block = "\n".join([
        f"This dataset has {args.frames} frames of one synthetic house, made by `tools/doc_pictures.py`:",
        "",
        "```",
        f"mpchair synth --out houses --houses 1 --seed {args.house_seed}                 # house {house}",
        f"mpchair generate --root houses --house {house} --frames {args.frames} --out dataset --seed "
        f"{args.dataset_seed} --workers {args.workers}",
        "mpchair stats --density dataset --config detector/configs/mpchair_dense.yaml --plot stats-density.png",
        "```",
        "",
        "| | min | median | mean | max |",
        "|---|---|---|---|---|",
        f"| **paper, Matterport-Chair test** | {MC.min:.5f} | **{MC.median:.5f}** | – | {MC.max:.5f} |",
        f"| {d['count']} synthetic frames, {dW} × {dH} | {d['min']:.5f} | **{d['median']:.5f}** | {d['mean']:.5f} | "
        f"{d['max']:.5f} |",
    ])

    b = m["boxes"]
    c = b["classes"]["Chair"]
    rejected = ", ".join(f"{k} {v}" for k, v in (b["rejected"] or {}).items()) or "none"
    c8 = m["boxes8"]["classes"]["Chair"]
    boxes_block = "\n".join([
        f"On the {b['frames']} synthetic frames (`mpchair stats --boxes dataset --plot stats-boxes.png`) the output "
        "reads:",
        "",
        f"* chairs: {c['count']} boxes, {b['boxes_per_frame']['mean']:.2f} per frame;",
        f"* size: l {c['l']['mean']:.3f} ± {c['l']['std']:.3f}, w {c['w']['mean']:.3f} ± {c['w']['std']:.3f}, "
        f"h {c['h']['mean']:.3f} ± {c['h']['std']:.3f} m;",
        f"* points per box: median {c['points']['median']:g} (min {c['points']['min']:g}, max "
        f"{c['points']['max']:g});",
        f"* distance: {c['distance']['min']:.2f}–{c['distance']['max']:.2f} m;",
        f"* rejected: {rejected}.",
    ])
    houses_block = "\n".join([
        f"More houses bring the mean back towards the anchor: {MULTI_HOUSES} houses (`mpchair synth --houses "
        f"{MULTI_HOUSES} --seed 0`, then",
        f"`generate --frames {MULTI_FRAMES} --seed 0` on all {MULTI_HOUSES}) give {c8['count']} boxes of "
        f"{c8['l']['mean']:.3f} × {c8['w']['mean']:.3f} × {c8['h']['mean']:.3f} m.",
    ])

    view_block = "\n".join([
        f"(`mpchair view dataset --frame {int(m['frame'])} --out view-frame.png --3d --size 1000 800`, with the "
        "default ceiling cut. Among",
        f"the frames whose chairs all have at least {MIN_SCAN_POINTS} scan points, `tools/doc_pictures.py` picks "
        "the one with the most",
        "chairs, so that no drawn box is empty.)",
    ])
    return {"kitti-density": kitti_block, "mpchair-density": density_block, "boxes": boxes_block,
            "boxes-houses": houses_block, "view-frame": view_block}  # fmt: skip


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (defaults: the seeds and sizes whose numbers docs/stats.md quotes)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out-dir", type=Path, default=ROOT / "docs" / "img", help="where the PNGs go (default docs/img)")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "doc-pictures",
                   help="work folder (default out/doc-pictures): houses/ and dataset/, both rebuilt on every run, "
                        "and the commands' JSON output")  # fmt: skip
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "stats.md",
                   help="the page whose marked blocks get the numbers (default docs/stats.md)")
    p.add_argument("--check", action="store_true",
                   help="make the numbers only (no pictures) and exit 1 if the doc's blocks differ")
    p.add_argument("--house-seed", type=int, default=1, help="mpchair synth --seed (default 1)")
    p.add_argument("--dataset-seed", type=int, default=0, help="mpchair generate --seed (default 0)")
    p.add_argument("--frames", type=int, default=48, help="frames to generate (default 48)")
    p.add_argument("--workers", type=int, default=2, help="generate workers (default 2; the bytes do not depend on it)")
    p.add_argument("--frame", help="frame for view-frame*.png (default: picked from manifest.json, see pick_frame)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """``tools/doc_pictures.py``: 0 when written (or, with ``--check``, current), 1 for a stale doc or a failed
    command, 2 on bad input (one ``error:`` line: the console scripts' error path)."""
    return run_script(lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    args = parse_args(argv)
    require_checkout()  # its defaults are the clone's docs/ and the vendored KITTI frames
    if not MPCHAIR.exists():
        raise InputError(f"{MPCHAIR} not found; run this with the venv's python (pip install -e .)")

    work = args.work.resolve()
    out_dir = args.out_dir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    if not args.check:
        out_dir.mkdir(parents=True, exist_ok=True)
    # generate resumes a dataset folder that already exists; starting afresh makes the pictures depend on the
    # seeds and options only, not on what an earlier run with other options left behind.
    for sub in ("houses", "dataset", "houses8", "dataset8"):
        shutil.rmtree(work / sub, ignore_errors=True)
    # Commands on the synthetic data run inside `work` with relative paths, because the figures' titles show the
    # dataset path as given: an absolute (temporary) path would change the pictures from one machine to the next.
    try:
        m = measure(work, args, None if args.check else out_dir)
        text = args.doc.read_text(encoding="utf-8")
        filled = fill_blocks(text, number_blocks(m, args), args.doc)
        if args.check:
            if filled != text:
                raise CommandError(f"{args.doc}: its numbers are stale; run python tools/doc_pictures.py")
            print(f"{args.doc}: every number is current")
            return 0
        house = m["house"]
        # No --zmax: the default ceiling cut (2 m above the floor), as a user gets it.
        view = run_json(["view", "dataset", "--frame", m["frame"], "--out", str(out_dir / "view-frame.png"), "--3d",
                         "--size", "1000", "800"], work, work / "view-frame.json")  # fmt: skip
        # Two levels side by side: a wide canvas, or the square default leaves half the picture blank.
        house_view = run_json(["view-house", "--root", "houses", "--house", house, "--dataset", "dataset",
                               "--out", str(out_dir / "view-house.png"), "--size", "1600", "860"],
                              work, work / "view-house.json")  # fmt: skip
    except json.JSONDecodeError as e:  # a command whose --json output is not JSON
        raise CommandError(f"a command's --json output is not JSON: {e}") from None
    write_text(args.doc, filled)
    gen, manifest = m["generate"], m["manifest"]
    kept = next(f for f in manifest["frames"] if f["frame"] == view["frame"])["kept"]
    lines = [
        f"house {house} (synth --seed {args.house_seed}), {gen['frames']} frames (generate --seed "
        f"{args.dataset_seed}): {gen['kept']} kept boxes, rejected {gen['rejected']}",
        density_line("mpchair density (512 x 768)", m["density"]),
        density_line("KITTI density (440 x 504)", m["kitti"]),
        *boxes_lines(m["boxes"]),
        f"view frame {view['frame']}: {view['points']} points, {view['boxes']} boxes, scan points per chair "
        f"{[k['scan_points'] for k in kept]}",
        f"view-house: {house_view['faces']} faces, {house_view['objects']} chairs, "
        f"{house_view['viewpoints']} viewpoints",
        f"pictures in {out_dir}, numbers in {args.doc}, JSON in {work}",
    ]
    print("\n".join(lines))
    return 0

