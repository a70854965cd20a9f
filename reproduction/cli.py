"""``make reproduce``: the Sparse PointPillars Matterport-Chair experiment end to end on synthetic houses, CPU-sized.

Steps (each one a list of exact ``mpchair`` / ``detector`` command lines, run as subprocesses and recorded):

    synth     mpchair synth              synthetic houses (Matterport3D release format)
    generate  mpchair generate           the dataset (mp3d-depth90 sensor, seeded 8 / 2 / 2 house split)
    stats     mpchair stats --density    D per frame at the paper's 768x512 geometry (test split)
    train     detector train             dense and sparse, the CPU-sized configs (mpchair_*_cpu.yaml)
    eval      detector eval              BEV / 3D AP at IoU 0.5 (val split): the KITTI protocol (Overall, where every
                                         chair counts as in the paper, then Easy / Moderate / Hard; R40 and R11) and
                                         the reference's own metric on the same result files (--protocol open3d-ml)
    bench     detector bench             per-component runtime at 768x512 (trained weights load at any grid size),
                                         under the default allocator and the reuse setting, with Open3D-ML's own
                                         PointPillars as a peer row when Open3D-ML is installed
    refhead   tools/bench_reference_head.py  dense / sparse total time with the reference's head layout (three NCHW
                                         1x1 convs) beside our fused head at 768x512: the ratio the paper's 4.6x is
    ops       detector ops               exact MACs vs Table I's bound at 768x512
    viz       detector viz-sparsity      the paper's Figs. 3-4 at 768x512
    curve     tools/bench_density.py     dense / sparse backbone runtime and op-count ratios against density D
                                         (clustered synthetic sites, random weights, D 0.002 .. 0.0246) at 768x512
    deploy    detector eval / bench      the trained models exported to ONNX Runtime / OpenVINO at every precision
              --runtime --precision      the CPU computes natively: val AP, runtime at 768x512, the CPU budget at
                                         1 Hz (AP drop vs speed; docs/deployment.md)
    ablation-bench  detector bench       the ablation configs beside dense and sparse at the KITTI geometry (the
                                         vendored KITTI frames) and at 768x512 (reproduction.ablations)
    report    docs/results.md            every table and figure, the commands, the paper's numbers beside ours
    record    docs/results-data/         the report's inputs (JSON, tables, training logs, figures, the dataset's
                                         manifest and fingerprint; no weights, no frames): the report can be written
                                         again, and steps added to the run, in a later session (--from-record)

Opt in (``--steps ablations,report``, ``make reproduce-ablations``): ``ablations`` trains and evaluates the paper's
ablations on this run's data (``--ablations``, ``--ablation-epochs``), then times them again with their weights.

``--weights committed`` (``make reproduce-runtime``): the train step trains nothing; it puts the accuracy study's
committed weights (``pretrained:dense`` / ``pretrained:sparse``, detector/pretrained) where every later step reads
a training, ``runs/<model>/`` (:mod:`reproduction.committed`: last.pt is the packed file, config.yaml its experiment,
``done`` its name, SHA-256 and study training), and the report and record say so. Only on the study's dataset (the
full / recipe scales at seed 0); a name not committed yet, or a file that is not the model its name says (its
state dict against ``mpchair_<model>_cpu.yaml``'s model), is one ``error:`` line before any step runs.
``--bench-runs N`` (full / recipe: 3): the bench step and the deploy step's runtime table run ``detector bench --runs
N``, N processes one after another, and the report quotes each headline ratio as the median with its min-max (the
refhead, curve, budget and ablation benches run once).

``--from-record DIR`` first copies a run record (``docs/results-data``: what the ``record`` step wrote) into the work
folder, so every step it recorded counts as done; with ``generate`` among the steps the dataset is made again and must
be byte for byte the recorded one (else exit 2). ``make reproduce-ablations`` does that: a later session adds the
ablations to the committed run without training the dense and sparse models again (reproduction.record).
A dry run copies nothing, but counts the record's files as there: it lists the steps the real run would run (and, for
a record made with committed weights, their install instead of a training).

A step whose outputs exist is skipped (``--force`` redoes it); ``detector train --resume`` continues a cut run (in
the precision it started with); ``--status`` says where a work folder stands and how long its training has left.
Before the first command it prints its estimate of how long the steps still to run take on this machine
(:mod:`reproduction.estimate`: the run record's measured command times, scaled to the scale's sizes and to this
machine's probe).

``--scale full`` (the default, ``make reproduce``) is the paper's experiment on a schedule chosen to fit one 3-hour
session of 2 cores together with ``make reproduce-stream``: 12 houses, 4,800 frames split by house = 3,200 train /
800 val / 800 test (8 / 2 / 2 houses, none shared), dense 4 epochs and sparse 5 (the paper's 200 / 250 ratio), in
bfloat16 autocast where the CPU has native
bf16 (AVX512-BF16 / AMX) and fp32 elsewhere (a dense step ~0.25 s in bf16 on 2 AVX512-BF16 cores, ~1.75 s in
fp32 on 2 AVX2-only ones: docs/benchmarks.md). ``--scale recipe`` is
the longer schedule, dense 16 / sparse 20 epochs (an estimated ~3.5 h of training on 2 native-bf16 cores and ~16 h
on 2 AVX2-only ones: steps x the step times measured 2026-12-01 / 02, docs/benchmarks.md): a GPU's job or a machine
that outlives a session. ``--scale small`` is a quick end-to-end check (2 houses, 300 frames, 2 epochs: 33.5 min on
a 2-core machine shared with other jobs, 2026-12-06); ``--scale medium`` 8 houses, 2,000 frames, 10 epochs.

Every command is printed before it runs and its own output passes through as it comes: the train step's ``detector
train`` runs without progress bars but prints its plan, the duration it measured on its first steps and one line per
epoch (and per validation).

Figures referenced by the report are copied next to it (``<results dir>/img/results-<scale>/``), so that the report
stays valid when ``out/`` is deleted.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from mpchair.core.clitools import run_script
from mpchair.core.doctable import write_doc_table
from mpchair.core.errors import InputError
from mpchair.core.limits import MAX_SEED, max_parallel
from reproduction.ablations import run_ablation_bench, run_ablations
from reproduction.checkout import ROOT, require_checkout
from reproduction.committed import WEIGHTS, check_committed, committed_runs, folder_conflict, study_dataset_problem
from reproduction.deploy import LIKE_FOR_LIKE_DOCS, LIKE_FOR_LIKE_MARKER, like_for_like
from reproduction.estimate import estimate, estimate_lines, recorded_times, this_machine, write_probe
from reproduction.record import (
    MAX_FILE_BYTES,
    check_dataset,
    check_record_dest,
    read_record,
    record_scale,
    restorable_files,
    restore_record,
    save_record,
)
from reproduction.report import write_report
from reproduction.results import ABLATIONS
from reproduction.runner import Runner
from reproduction.scales import SCALES, Scale, cpu_has_native_bf16
from reproduction.status import other_scales, status_lines
from reproduction.steps import COMMAND_STEPS, OPT_IN_STEPS, STEPS, Plan, run_generate, step_outputs


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", choices=sorted(SCALES), default=None,
                   help="full (default): the paper's experiment on synthetic houses, on a one-session schedule "
                        "(dense 4 / sparse 5 epochs); recipe: dense 16 / sparse 20 epochs (an estimated ~3.5 h of "
                        "training on 2 native-bf16 cores, ~16 h on 2 AVX2-only ones); small: a quick check that "
                        "every step runs (33.5 min on a shared 2-core machine). Every run prints its own estimate "
                        "for this machine before it starts")
    p.add_argument("--steps", default=",".join(STEPS),
                   help=f"comma-separated subset of {','.join(STEPS)}, or the opt-in {','.join(OPT_IN_STEPS)} "
                        "(the ablations' trainings: make reproduce-ablations)")
    p.add_argument("--out", type=Path, default=None, help="work folder (default out/reproduce-<scale>)")
    p.add_argument("--results", type=Path, default=None,
                   help="report file (default: docs/results.md for --scale full, <work folder>/results.md otherwise)")
    p.add_argument("--threads", type=int, default=2, help="torch threads for train / eval / bench")
    p.add_argument("--workers", type=int, default=2, help="mpchair generate worker processes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="redo steps whose outputs exist")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    p.add_argument("--epochs", type=int, default=None,
                   help="the dense model's training epochs instead of the scale's (full: 4, recipe: 16, medium: 10, "
                        "small: 2); the sparse model trains ceil(1.25x) as many, the paper's 250 / 200 ratio")
    p.add_argument("--precision", choices=["fp32", "bf16", "auto"], default=None,
                   help="training precision of both models instead of the scale's (full: auto = bf16 where the CPU "
                        "computes bfloat16 natively, AVX512-BF16 / AMX, else fp32; medium / small: the "
                        "configs', fp32); bf16 = bfloat16 autocast, ~1.85x faster dense steps on CPUs with "
                        "AVX512-BF16 / AMX, slower on CPUs without")
    p.add_argument("--note", action="append", default=[],
                   help="a sentence for the report's opening paragraph, e.g. how this run deviated (repeatable)")
    p.add_argument("--status", action="store_true",
                   help="print where the work folder's reproduction stands (each step; each model's training step, "
                        "pace and time left; whether a training runs now) and exit")
    p.add_argument("--ablations", default=",".join(ABLATIONS),
                   help="the ablations the ablations step trains and evaluates (comma-separated; default all four)")
    p.add_argument("--ablation-epochs", type=int, default=None,
                   help="training epochs of each ablation (default: the sparse model's of the scale)")
    p.add_argument("--from-record", type=Path, default=None, metavar="DIR",
                   help="restore a run record (the record step's folder, e.g. docs/results-data) into the work folder "
                        "first, so its steps count as done; a regenerated dataset must equal the recorded one")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="where the record step writes (default: docs/results-data for --scale full / recipe, "
                        "<work folder>/record otherwise)")
    p.add_argument("--bench-frames", type=int, default=None,
                   help="frames per `detector bench` trial instead of the scale's (full: 30, medium: 20)")
    p.add_argument("--bench-runs", type=int, default=None,
                   help="runs of the bench step's and the deploy step's runtime tables (`detector bench --runs N`, "
                        "each run a process of its own; the report quotes the ratios' median and min-max) instead "
                        "of the scale's (full / recipe: 3, small / medium: 1)")
    p.add_argument("--weights", choices=WEIGHTS, default=None,
                   help="train (default; a work folder that holds the committed weights keeps them): the train step "
                        "trains dense and sparse here; committed: it trains nothing and takes the accuracy study's "
                        "committed weights (pretrained:dense / pretrained:sparse, detector/pretrained) for every later "
                        "step (full / recipe scales: the study's dataset); make reproduce-runtime")
    p.add_argument("--pretrained", type=Path, default=None, metavar="DIR",
                   help="with --weights committed: the folder of the packed weights and their index.json instead of "
                        "the package's detector/pretrained (tools/pack_pretrained.py --out DIR)")
    return p


def _scale(args: argparse.Namespace) -> Scale:
    """The scale with the command line's overrides (``auto`` precision resolved on this CPU); an
    :class:`InputError` for a bad override."""
    sc = SCALES[args.scale]
    if args.epochs is not None:
        if args.epochs < 1:
            raise InputError("--epochs must be >= 1")
        sc = dataclasses.replace(sc, epochs=args.epochs)
    if args.precision is not None:
        sc = dataclasses.replace(sc, precision=args.precision)
    if sc.precision == "auto":
        # bf16 autocast is ~1.85x faster per dense step with AVX512-BF16 but ~15x slower without it (measured on an
        # AVX2-only AMD EPYC: 12 s vs 0.85 s per dense step), so it is only chosen where the CPU has it.
        sc = dataclasses.replace(sc, precision="bf16" if cpu_has_native_bf16() else "fp32")
        found = "found" if sc.precision == "bf16" else "not found"
        print(f"training precision: {sc.precision} (auto: native bfloat16 {found})")
    if args.bench_frames is not None:
        if args.bench_frames < 1:
            raise InputError("--bench-frames must be >= 1")
        sc = dataclasses.replace(sc, bench_frames=args.bench_frames)
    return _bench_runs(args, sc)


def _bench_runs(args: argparse.Namespace, sc: Scale) -> Scale:
    """The scale with ``--bench-runs`` applied (detector bench takes 1 to 100)."""
    if args.bench_runs is None:
        return sc
    if not 1 <= args.bench_runs <= 100:
        raise InputError(f"--bench-runs takes 1 to 100, got {args.bench_runs}")
    return dataclasses.replace(sc, bench_runs=args.bench_runs)


def _weights(args: argparse.Namespace, out: Path, sc: Scale, steps: list[str]) -> str:
    """The weights this invocation's steps use: ``--weights``, else the work folder's (committed weights restored from
    a record stay committed; a dry run, which restores nothing, reads them from the ``--from-record`` record), else
    ``train``; an :class:`InputError` (one line, before any step runs) for committed weights that are not in
    detector/pretrained, a scale whose dataset is not the one they were trained on, or a work folder holding other
    weights than asked for."""
    held = committed_runs(out) or (committed_runs(args.from_record) if args.from_record is not None and args.dry_run
                                   else {})
    weights = args.weights or ("committed" if held else "train")
    shas = None
    if weights == "committed":
        problem = study_dataset_problem(sc, args.seed)
        if problem:
            raise InputError(problem)
        shas = check_committed(args.pretrained) if "train" in steps else None
    if not args.force:
        conflict = folder_conflict(out, weights, shas)
        if conflict:
            raise InputError(conflict)
    return weights


def _recorded_run(args: argparse.Namespace, steps: list[str], scale_given: bool) -> tuple[Scale, list[str]]:
    """``--from-record``: the recorded run's scale (``args.scale`` set to it) and notes, with this invocation's notes
    and, when it adds steps, one saying when and how (an :class:`InputError` for a record that does not fit). The
    steps added belong to that run, and its report is rewritten whole."""
    meta = read_record(args.from_record)
    if scale_given and meta.get("scale") != args.scale:
        raise InputError(f"--scale {args.scale}, but the record {args.from_record} is of a {meta.get('scale')}-scale "
                         "run")
    args.scale, sc = meta["scale"], record_scale(meta)
    sc = _bench_runs(args, sc)
    if args.precision is not None:
        sc = dataclasses.replace(sc, precision=args.precision)
    elif sc.precision == "bf16" and not cpu_has_native_bf16():
        # the recorded run's bf16 would be emulated here (~15x slower per step): the added trainings run fp32
        print("training precision: fp32 (the record's bf16 is not native on this CPU; the report says so)")
        sc = dataclasses.replace(sc, precision="fp32")
    added = [s for s in steps if s not in ("report", "record")]
    later = ([f"Steps {', '.join(added)} ran later ({time.strftime('%Y-%m-%d')}) from the run record "
              f"{args.from_record} (tools/reproduce.py --from-record), training precision "
              f"{sc.precision or 'the configs'}"
              + (": the dataset was regenerated and checked byte for byte against the record's" if "generate"
                 in steps else "") + "; the other steps' outputs are the record's."] if added else [])
    return sc, [*meta.get("notes", []), *args.note, *later]


def _estimate(plan: Plan, record: Path) -> list[str]:
    """The lines saying how long the steps still to run will take here, from ``record``'s measured times and (unless
    a dry run, which writes nothing) this machine's probe (reproduction.estimate); none without a record."""
    rec = recorded_times(record)
    if rec is None:
        return [f"estimate: none (no run record with a commands.log at {record})"]
    probe = None if plan.dry_run else write_probe(plan.out, plan.threads)
    here = this_machine()
    if probe is not None and (probe.get("cpu"), probe.get("logical_cpus")) != (here["cpu"], here["logical_cpus"]):
        probe = None  # the work folder's probe is an earlier machine's: its steps are that machine's too
    outputs = step_outputs(plan.out)
    done = set() if plan.force else {s for s in plan.steps if s in outputs and all(
        plan.has(p) for p in outputs[s].values())}
    # committed weights: the train step copies files, none of the record's training time
    steps = [s for s in plan.steps if s != "train" or plan.weights == "train"]
    est = estimate(rec, plan.scale, steps, here, None if probe is None else probe["probe_s"])
    return estimate_lines(est, done)


def _record_dest(args: argparse.Namespace, out: Path) -> Path:
    """Where the record step writes: ``--record``, else docs/results-data for the issue's scales, else OUT/record."""
    return args.record or (ROOT / "docs" / "results-data" if args.scale in ("full", "recipe") else out / "record")


def main(argv: list[str] | None = None) -> int:
    """``tools/reproduce.py``: run the steps asked for in the work folder and write the report; 2 on a bad option
    or a file of the work folder or record that cannot be read (one ``error:`` line naming it, no traceback: the
    console scripts' error path)."""
    return run_script(lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    require_checkout()  # it writes the clone's docs/: refused, in one line, anywhere else
    scale_given, args.scale = args.scale is not None, args.scale or "full"
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    bad = [s for s in steps if s not in (*STEPS, *OPT_IN_STEPS)]
    if bad:
        raise InputError(f"unknown step(s) {bad}; choose from {list(STEPS + OPT_IN_STEPS)}")
    ablations = tuple(a.strip() for a in args.ablations.split(",") if a.strip())
    if not ablations or [a for a in ablations if a not in ABLATIONS] or (args.ablation_epochs or 1) < 1:
        raise InputError(f"--ablations takes a comma-separated subset of {','.join(ABLATIONS)} and --ablation-epochs "
                         "a number >= 1")
    most = max_parallel()
    if not (1 <= args.threads <= most and 1 <= args.workers <= most and 0 <= args.seed <= MAX_SEED):
        raise InputError(f"--threads and --workers take 1 to {most} (4 per core here), --seed 0 to {MAX_SEED}; got "
                         f"{args.threads}, {args.workers}, {args.seed}")
    out = (args.out or ROOT / "out" / f"reproduce-{args.scale}").resolve()
    if args.status:
        others = {} if args.out is not None else other_scales(out, args.scale, tuple(sorted(SCALES)))
        if not out.is_dir() and not scale_given and len(others) == 1:
            # `--status` as README shows it while another scale runs (make reproduce SCALE=small): that run
            ((scale, out),) = others.items()
            print(f"(no --scale given and no {args.scale}-scale work folder: the {scale}-scale one)")
            others = {}
        # a file of the work folder that cannot be read is an InputError naming it: never a hang or a traceback
        print("\n".join(status_lines(out, others)))
        return 0
    if args.from_record is not None:
        sc, notes = _recorded_run(args, steps, scale_given)
        out = (args.out or ROOT / "out" / f"reproduce-{args.scale}").resolve()
    else:
        sc, notes = _scale(args), list(args.note)
    if "record" in steps:  # before any step runs: a --record folder that is not a record is never replaced
        check_record_dest(_record_dest(args, out))
    would_restore: frozenset[Path] = frozenset()
    if args.from_record is not None:  # a record refused leaves no work folder behind
        files = restorable_files(args.from_record, with_dataset="generate" not in steps)
        # a dry run restores nothing: what the real run restores first counts as there for its steps
        would_restore = frozenset(out / rel for rel in files) if args.dry_run else frozenset()
        if args.dry_run:
            print(f"would restore {sum(not p.exists() for p in would_restore)} file(s) of the record "
                  f"{args.from_record} into {out} first (a dry run copies nothing)")
    out.mkdir(parents=True, exist_ok=True)
    if args.from_record is not None and not args.dry_run:
        restored = restore_record(args.from_record, out, with_dataset="generate" not in steps)
        print(f"restored {len(restored)} file(s) of the record {args.from_record} into {out}")
    weights = _weights(args, out, sc, steps)
    plan = Plan(out=out, scale=sc, steps=tuple(steps), threads=args.threads, workers=args.workers, seed=args.seed,
                force=args.force, dry_run=args.dry_run, ablations=ablations, ablation_epochs=args.ablation_epochs,
                weights=weights, pretrained=args.pretrained.resolve() if args.pretrained else None,
                restored=would_restore)
    for line in _estimate(plan, args.from_record or ROOT / "docs" / "results-data"):
        print(line, flush=True)
    r = Runner(args.dry_run, out / "commands.log")
    t0 = time.perf_counter()
    for run_step in (*COMMAND_STEPS, run_ablations, run_ablation_bench):
        run_step(plan, r)
        if run_step is run_generate and args.from_record is not None and "generate" in steps and not args.dry_run:
            check_dataset(args.from_record, plan.data)  # what follows must run on the recorded run's dataset
    total = time.perf_counter() - t0
    # only the full and recipe scales replace the committed report and record; a quick check keeps both in its work
    # folder
    full = args.scale in ("full", "recipe")
    if "report" in steps and not args.dry_run:
        results = args.results or (ROOT / "docs" / "results.md" if full else out / "results.md")
        write_report(results, out, plan.res, args.scale, sc, notes=notes)
        print(f"wrote {results}")
        table = like_for_like(plan.res)
        if full and args.results is None and table:  # the table README.md and two docs lead with
            for doc in LIKE_FOR_LIKE_DOCS:
                # a doc that lost its markers is an InputError naming it, and stays as it was
                write_doc_table(ROOT / doc, "\n".join(table) + "\n", LIKE_FOR_LIKE_MARKER)
            print(f"wrote its like-for-like table into {', '.join(LIKE_FOR_LIKE_DOCS)}")
    if "record" in steps and not args.dry_run:
        dest = _record_dest(args, out)
        too_big = save_record(out, dest, args.scale, sc, notes)
        for rel in too_big:
            print(f"record: left out {rel} (over {MAX_FILE_BYTES >> 20} MB)")
        print(f"wrote the run record {dest}")
    print(f"total time {total / 60:.1f} min ({args.scale} scale, steps {','.join(steps)})")
    return 0
