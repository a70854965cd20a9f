"""``tools/accuracy_study.py`` (``make accuracy-study``): the accuracy study, one session's share at a time.

Steps, in order (``--steps`` picks a subset):

    restore   copy the record's trainings into the work folder (a cut training continues from its ``last.pt``)
    dataset   mpchair synth + generate: the full scale's 12 houses, 4,800 frames split 8 / 2 / 2 by house; refused
              (exit 2) unless byte for byte the record's dataset or one accepted as its equivalent on another class
              of CPU (--accept-dataset; reproduction/study_dataset.py)
    train     detector train of the next unfinished training (or ``--training``), for at most ``--minutes``: it stops
              at the plateau rule, the 60-epoch cap, or the time limit (then it is saved and resumes next session)
    test      detector eval on the test split of every finished, untested training (KITTI + Open3D-ML protocol)
    record    the work folder's state into the record (docs/results-data/accuracy): run summaries, a cut training's
              resumable last.pt, test detections; then the analysis: accuracy.md and curves.png into the record,
              its machine-readable summary beside it (docs/results-data/accuracy.json: <record>.json)

A full study is 10 trainings (dense and sparse x seeds 0-2, the four ablations x seed 0); docs/results.md,
"Accuracy", says how many are in the record and what the gap's interval supports.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from reproduction.checkout import ROOT, require_checkout
from reproduction.record import dataset_fingerprint
from reproduction.runner import Runner
from reproduction.study import (
    Study,
    by_name,
    done_trainings,
    make_dataset,
    next_training,
    read_study_record,
    read_zip_texts,
    record_has_test_of,
    restore,
    save,
    summary_path,
    test,
    train,
    trainings,
)
from reproduction.study_dataset import accepted, cpu_description, dataset_parts, equivalence_problems

STEPS = ("restore", "dataset", "train", "test", "record")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=None, help="work folder (default out/accuracy)")
    p.add_argument("--record", type=Path, default=None,
                   help="the study's record (default docs/results-data/accuracy); the summary is written beside "
                        "it as <record>.json")
    p.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated subset of {','.join(STEPS)}")
    p.add_argument("--training", default=None,
                   help="the training to run (default: the first unfinished one of "
                        f"{', '.join(t.name for t in trainings())})")
    p.add_argument("--minutes", type=float, default=100.0,
                   help="wall-time limit of this session's training (default 100): it saves and stops there")
    p.add_argument("--threads", type=int, default=2, help="torch threads for train / eval")
    p.add_argument("--workers", type=int, default=2, help="mpchair generate worker processes")
    p.add_argument("--resamples", type=int, default=200, help="bootstrap resamples of the test frames")
    p.add_argument("--note", action="append", default=[],
                   help="a sentence for the record's notes (e.g. the machine a training ran on); repeatable")
    p.add_argument("--accept-dataset", action="store_true",
                   help="take a regenerated dataset whose sha256 differs from the record's if its manifest, splits "
                        "and test labels equal the record's (float bits that differ between CPU classes), and record "
                        "its fingerprint as an equivalent with this machine's name")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    p.add_argument("--status", action="store_true", help="print each training's state in the record and exit")
    return p


def _status(study: Study) -> list[str]:
    meta = read_study_record(study.record)
    states = meta.get("trainings", {})
    lines = [f"accuracy study record {study.record}: {sum(s.get('status') == 'done' for s in states.values())} of "
             f"{len(trainings())} trainings finished"]
    for t in trainings():
        s = states.get(t.name, {})
        lines.append(f"  {t.name:22s} {s.get('status', 'not started'):12s}"
                     + (" tested" if s.get("tested") else ""))
    return lines


def main(argv: list[str] | None = None) -> int:
    """Run the steps asked for; 2 on bad input (one ``error:`` line, the console scripts' error path)."""
    return run_script(lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    if [s for s in steps if s not in STEPS] or not steps:
        raise InputError(f"--steps takes a comma-separated subset of {','.join(STEPS)}")
    if not (args.minutes > 0 and args.minutes < 1e6) or not 1 <= args.threads <= 256 or args.resamples < 1:
        raise InputError("--minutes must be > 0, --threads in 1..256 and --resamples >= 1")
    require_checkout()  # it writes the clone's docs/: refused, in one line, anywhere else
    out = args.out or ROOT / "out" / "accuracy"
    record = args.record or ROOT / "docs" / "results-data" / "accuracy"
    study = Study(out=out.resolve(), record=record.resolve(), threads=args.threads, workers=args.workers)
    if args.status:
        print("\n".join(_status(study)))
        return 0
    chosen = by_name(args.training) if args.training else None
    return _run(study, steps, chosen, args)


def _check_dataset(study: Study, fingerprint: str, accept: bool) -> dict | None:
    """None when the record takes this dataset as it is; with ``accept``, the equivalence entry to record for a
    dataset that differs only in float bits; otherwise an InputError that says which."""
    meta = read_study_record(study.record)
    want = meta.get("dataset_sha256")
    if not want or accepted(meta, fingerprint):
        return None
    head = (f"{study.data} is not byte for byte the dataset of the record {study.record} (sha256 {fingerprint[:12]} "
            f"vs {want[:12]})")
    problems = equivalence_problems(study.data, study.record, read_zip_texts(study.record / "test_labels.zip"))
    if problems:
        raise InputError(f"{head}, and not an equivalent: {'; '.join(problems[:5])}. The code, houses or seed that "
                         "made it differ, so trainings on it would not belong to the study")
    if not accept:
        raise InputError(f"{head}, though its manifest, splits and test labels equal the record's: float bits that "
                         "differ between CPU classes (docs/generate.md, 'Determinism'). Re-run with --accept-dataset "
                         "to record it as an equivalent made on this machine")
    cpu = cpu_description()
    print(f"[dataset] accepted {fingerprint[:12]} as an equivalent of {want[:12]} (made on {cpu})")
    return {"cpu": cpu, "date": time.strftime("%Y-%m-%d", time.gmtime()),
            "evidence": "manifest (less its frame list: every total of frames, points, boxes kept and rejected per "
                        "reason), ImageSets and every test label file equal to the record's",
            "parts_sha256": dataset_parts(study.data)}


def _run(study: Study, steps: list[str], chosen, args: argparse.Namespace) -> int:
    t0 = time.monotonic()
    study.out.mkdir(parents=True, exist_ok=True)
    r = Runner(args.dry_run, study.out / "commands.log")
    if "restore" in steps and not args.dry_run:
        names = restore(study)
        print(f"restored {len(names)} training(s) from {study.record}: {', '.join(names) or 'none'}")
    fingerprint, equivalent = None, None
    if "dataset" in steps:
        make_dataset(study, r)
        if not args.dry_run:
            fingerprint = dataset_fingerprint(study.data)
            equivalent = _check_dataset(study, fingerprint, args.accept_dataset)
    if "train" in steps:
        t = chosen or next_training(study, done_trainings(study))
        if t is None:
            print("every training of the study is finished")
        else:
            left = args.minutes - (time.monotonic() - t0) / 60.0
            print(f"[train] {t.name} for at most {max(left, 1.0):.0f} min")
            finished = train(study, t, r, max(left, 1.0))
            print(f"[train] {t.name}: {'finished' if finished else 'not finished: resumes next session'}")
    if "test" in steps:
        for t in trainings():
            if study.done(t) and not study.tested(t) and not record_has_test_of(study, t):
                test(study, t, r)
    if "record" in steps and not args.dry_run:
        written = save(study, fingerprint, tuple(args.note), equivalent)
        print(f"record: wrote {len(written)} file(s) into {study.record}")
        from reproduction.study_report import write_analysis

        data = write_analysis(study.record, args.resamples)
        print(f"record: {summary_path(study.record)} ({len(data['trainings'])} training(s))")
    return 0
