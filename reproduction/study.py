"""The accuracy study (``tools/accuracy_study.py``, ``make accuracy-study``): three plateau-trained seeds of the dense
and the sparse model and one of each ablation, on the house-disjoint dataset of the full scale, tested with a
confidence interval; one training per session, accumulated in a committed record.

Work folder (default ``out/accuracy``)::

    houses/  dataset/                    the full scale's 12 synthetic houses and their 8 / 2 / 2 house-split dataset
    configs/<training>.yaml              the training's experiment: the model's CPU config + :data:`STUDY_TRAIN`
    runs/<training>/                     detector train's run folder (``done`` once the plateau rule or cap ended it)
    test/<training>/                     detector eval on the test split (metrics.json, open3d_ml.json, data/*.txt)
    commands.log

Record (default ``docs/results-data/accuracy``), what a later session restores and adds to: ``record.json`` (dataset
fingerprint, splits, each training's state), the dataset's manifest (less its frame list) and ImageSets, per training
``runs/<training>/{config.yaml, metrics.jsonl (epoch / eval / end records), done}`` and, while it is unfinished, its
resumable ``last.pt``; per tested training ``test/<training>/{metrics.json, open3d_ml.json, detections.zip}``;
``test_labels.zip`` (the test split's ground truth, so the analysis runs without the dataset); ``accuracy.md`` and
``curves.png`` (:mod:`reproduction.study_report`). The analysis's machine-readable summary sits beside the record
folder, named after it (:func:`summary_path`: ``docs/results-data/accuracy.json`` for the default record).
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import yaml

from mpchair.core.atomic import write_bytes, write_text
from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from reproduction.checkout import ROOT
from reproduction.results import ABLATIONS, OPEN3D_ML_JSON, end_record
from reproduction.runner import BIN, REUSE_ENV, Runner
from reproduction.scales import SCALES
from reproduction.steps import CONFIGS, Plan, run_generate, run_synth

#: The seeds of the dense and the sparse model; the ablations train seed 0 only.
SEEDS = (0, 1, 2)
MODELS = ("dense", "sparse")
#: The study's training settings on top of each model's CPU config (docs/training.md, "Trained to a plateau"):
#: fp32 (bf16 is native on some of this project's machines only, and a training continues on whichever machine the
#: next session gets), the plateau schedule (1 epoch warm-up, constant LR, x0.1 at the first plateau of the
#: validation 3D AP, stop at the second), validation every epoch, a 60-epoch cap, a checkpoint every 10 epochs.
STUDY_TRAIN = {"precision": "fp32", "schedule": "plateau", "eval_every": 1, "epochs": 60, "checkpoint_every": 10,
               "warmup_epochs": 1.0, "plateau_patience": 5, "plateau_min_delta": 1.0, "plateau_decays": 1,
               "plateau_factor": 0.1}
RECORD_JSON = "record.json"


def summary_path(record: Path) -> Path:
    """The study's machine-readable summary of record folder ``record``: ``<record>.json`` beside it (the default
    record docs/results-data/accuracy gives docs/results-data/accuracy.json, where issue 44 asks for it)."""
    return record.parent / f"{record.name}.json"

#: A zip member larger than this is refused when the record is read (a result file is a few kB).
MAX_MEMBER_BYTES = 1 << 20


@dataclasses.dataclass(frozen=True)
class Training:
    """One training of the study: ``model`` (``dense``, ``sparse`` or an ablation name) and its ``seed``."""

    model: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.model}_s{self.seed}"

    @property
    def base_config(self) -> Path:
        return CONFIGS / f"mpchair_{self.model}_cpu.yaml"


def trainings() -> tuple[Training, ...]:
    """Every training of the study, in the order sessions take them: seed 0 of dense and sparse first (their weights
    are the committed ones), then seeds 1 and 2, then the ablations."""
    return (*(Training(m, s) for s in SEEDS for m in MODELS), *(Training(a, 0) for a in ABLATIONS))


def by_name(name: str) -> Training:
    """The training called ``name`` (``dense_s0``, ...); an :class:`InputError` naming the choices otherwise."""
    for t in trainings():
        if t.name == name:
            return t
    raise InputError(f"--training: unknown training {name!r} (choose from {', '.join(t.name for t in trainings())})")


def study_config(t: Training) -> dict:
    """The experiment of training ``t``: its model's CPU config with :data:`STUDY_TRAIN` and its seed."""
    from detector.config import experiment_from_dict, load_experiment
    from mpchair.core.config import to_dict

    # through the validated loader, so the study's file is the resolved experiment whatever the YAML's layout
    cfg = json.loads(json.dumps(to_dict(load_experiment(t.base_config))))
    cfg["train"] = {**cfg["train"], **STUDY_TRAIN, "seed": t.seed}
    experiment_from_dict(cfg, source=str(t.base_config))  # the overrides must be valid too
    return cfg


@dataclasses.dataclass(frozen=True)
class Study:
    """The work folder ``out`` and the record folder ``record`` of a study run, and its torch threads / generate
    workers; the paths of its parts."""

    out: Path
    record: Path
    threads: int = 2
    workers: int = 2

    @property
    def plan(self) -> Plan:
        """The full scale's synth / generate plan in this work folder (the same houses and dataset bytes)."""
        return Plan(out=self.out, scale=SCALES["full"], steps=("synth", "generate"), threads=self.threads,
                    workers=self.workers)

    @property
    def data(self) -> Path:
        return self.out / "dataset"

    def config(self, t: Training) -> Path:
        return self.out / "configs" / f"{t.name}.yaml"

    def run(self, t: Training) -> Path:
        return self.out / "runs" / t.name

    def test(self, t: Training) -> Path:
        return self.out / "test" / t.name

    def done(self, t: Training) -> bool:
        return (self.run(t) / "done").is_file()

    def tested(self, t: Training) -> bool:
        return (self.test(t) / "metrics.json").is_file() and (self.test(t) / "data").is_dir()


def make_dataset(study: Study, r: Runner) -> None:
    """The full scale's houses and dataset in the work folder (skipped where they exist)."""
    run_synth(study.plan, r)
    run_generate(study.plan, r)


def train(study: Study, t: Training, r: Runner, minutes: float) -> bool:
    """Train (or continue) ``t`` for at most ``minutes`` of wall time; True when the run ended (plateau or cap), which
    its ``done`` marker then records."""
    config = study.config(t)
    if not config.is_file():
        write_text(config, yaml.safe_dump(study_config(t), sort_keys=False))
    run = study.run(t)
    cmd = [str(BIN / "detector"), "train", "--config", str(config), "--data", str(study.data), "--out", str(run),
           "--threads", str(study.threads), "--no-progress", "--max-minutes", f"{minutes:.1f}"]
    if (run / "last.pt").is_file():
        cmd.append("--resume")
    # glibc otherwise returns every large freed tensor to the OS and page-faults it back in on the next step
    r.run(cmd, env=REUSE_ENV)
    if r.dry_run or end_record(run) is None:
        return False
    write_text(run / "done", "trained\n")
    return True


def test(study: Study, t: Training, r: Runner) -> None:
    """``detector eval`` of a finished training on the test split (KITTI protocol), then the reference's Open3D-ML
    metric on the same result files."""
    out = study.test(t)
    r.run([str(BIN / "detector"), "eval", "--config", str(study.config(t)), "--data", str(study.data),
           "--checkpoint", str(study.run(t) / "last.pt"), "--split", "test", "--out", str(out), "--threads",
           str(study.threads)])
    r.run([str(BIN / "detector"), "eval", "--labels", str(study.data / "training" / "label_2"), "--results",
           str(out / "data"), "--split", str(study.data / "ImageSets" / "test.txt"), "--classes", "Chair",
           "--protocol", "open3d-ml", "--json"], stdout=out / OPEN3D_ML_JSON)


def next_training(study: Study, done: set[str]) -> Training | None:
    """The first training of :func:`trainings` that is not done (in the work folder or the record)."""
    return next((t for t in trainings() if t.name not in done), None)


# --- the record -------------------------------------------------------------------------------------------------------

def _zip_folder(folder: Path, ids: list[str]) -> bytes:
    """``folder/<id>.txt`` of every id, as a deterministic zip (fixed timestamps, sorted names)."""
    import io

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for i in sorted(ids):
            info = zipfile.ZipInfo(f"{i}.txt", date_time=(2026, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, (folder / f"{i}.txt").read_bytes())
    return buf.getvalue()


def read_zip_texts(path: Path) -> dict[str, str]:
    """Frame id -> text of a record's zip of per-frame files (members capped at :data:`MAX_MEMBER_BYTES`)."""
    out = {}
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            if info.file_size > MAX_MEMBER_BYTES or "/" in info.filename or not info.filename.endswith(".txt"):
                raise InputError(f"unexpected member {info.filename!r} ({info.file_size} bytes)", path)
            out[info.filename[:-4]] = z.read(info).decode("utf-8")
    return out


def _log_summary(metrics: Path) -> str:
    """A run's metrics.jsonl without its per-step records (the record keeps epochs, evaluations and the end)."""
    lines = []
    for line in metrics.read_text(encoding="utf-8").splitlines():
        try:
            kind = json.loads(line).get("kind")
        except (json.JSONDecodeError, AttributeError):
            continue
        if kind != "step":
            lines.append(line)
    return "".join(line + "\n" for line in lines)


def completed_epochs(last: Path) -> int:
    """The completed epochs of a run's ``last.pt`` (0 when there is none)."""
    if not last.is_file():
        return 0
    import torch

    return int(torch.load(last, map_location="cpu", weights_only=True).get("epoch", 0))


def read_study_record(record: Path) -> dict:
    """The record's ``record.json`` ({} when there is none yet)."""
    path = record / RECORD_JSON
    if not path.is_file():
        return {}
    meta = load_json(path, "accuracy-study record")
    if not isinstance(meta, dict) or not isinstance(meta.get("trainings", {}), dict):
        raise InputError("not an accuracy-study record", path)
    return meta


def save(study: Study, fingerprint: str | None, notes: tuple[str, ...] = (),
         equivalent: dict | None = None) -> list[str]:
    """Add the work folder's state to the record: dataset files, every training's run summary (and ``last.pt`` while
    unfinished; removed from the record once done), every tested training's results. Files of the record that this
    work folder does not have are kept (another session's trainings). The record keeps the fingerprint it started
    with; ``equivalent`` (machine, evidence, parts) records ``fingerprint`` as an accepted equivalent of it
    (:mod:`reproduction.study_dataset`). The paths written."""
    rec, written = study.record, []

    def put(rel: str, data: bytes) -> None:
        write_bytes(rec / rel, data)
        written.append(rel)

    meta = read_study_record(rec)
    manifest_path = study.data / "manifest.json"
    if manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text())
        frames = manifest.pop("frames", [])
        manifest["frames_left_out_of_the_record"] = len(frames)
        put("dataset/manifest.json", (json.dumps(manifest, indent=1) + "\n").encode())
        for p in sorted((study.data / "ImageSets").glob("*.txt")):
            put(f"dataset/ImageSets/{p.name}", p.read_bytes())
        meta["split_houses"] = manifest.get("split_houses")
    meta["dataset_sha256"] = meta.get("dataset_sha256") or fingerprint
    if equivalent is not None and fingerprint and fingerprint != meta["dataset_sha256"]:
        meta["dataset_equivalents"] = {**(meta.get("dataset_equivalents") or {}), fingerprint: equivalent}
    test_split = study.data / "ImageSets" / "test.txt"
    if test_split.is_file() and not (rec / "test_labels.zip").is_file():
        put("test_labels.zip", _zip_folder(study.data / "training" / "label_2", test_split.read_text().split()))
    states = dict(meta.get("trainings", {}))
    for t in trainings():
        run = study.run(t)
        if not (run / "metrics.jsonl").is_file():
            continue
        if not study.done(t) and completed_epochs(run / "last.pt") < 1:
            # less than an epoch is minutes on a fast machine: not worth a ~55 MB checkpoint in the history
            print(f"record: {t.name} is left out (cut before its first epoch ended; it starts afresh next time)")
            continue
        put(f"runs/{t.name}/config.yaml", (run / "config.yaml").read_bytes())
        put(f"runs/{t.name}/metrics.jsonl", _log_summary(run / "metrics.jsonl").encode())
        if study.done(t):
            put(f"runs/{t.name}/done", b"trained\n")
            (rec / "runs" / t.name / "last.pt").unlink(missing_ok=True)  # ours: the record step wrote it
        elif (run / "last.pt").is_file():
            put(f"runs/{t.name}/last.pt", (run / "last.pt").read_bytes())
        state = {"status": "done" if study.done(t) else "partial", "model": t.model, "seed": t.seed}
        if states.get(t.name, {}).get("tested"):  # tested in an earlier session: its files are in the record
            state["tested"] = True
        if study.tested(t):
            out = study.test(t)
            ids = sorted(p.stem for p in (out / "data").glob("*.txt"))
            put(f"test/{t.name}/detections.zip", _zip_folder(out / "data", ids))
            for name in ("metrics.json", OPEN3D_ML_JSON):
                if (out / name).is_file():
                    put(f"test/{t.name}/{name}", (out / name).read_bytes())
            state["tested"] = True
        states[t.name] = state
    meta["trainings"] = states
    meta["format"] = 1
    meta["notes"] = [*meta.get("notes", []), *notes]
    write_text(rec / RECORD_JSON, json.dumps(meta, indent=1, sort_keys=True) + "\n")
    log = study.out / "commands.log"
    if log.is_file():
        old = (rec / "commands.log").read_text() if (rec / "commands.log").is_file() else ""
        new = log.read_text().replace(str(ROOT) + "/", "")
        if not old.endswith(new):
            write_text(rec / "commands.log", old + new)
        write_text(log, "")  # appended to the record once
    return written


def restore(study: Study) -> list[str]:
    """Copy the record's runs into the work folder where it lacks them: a finished training's summary and ``done``,
    an unfinished one's ``config.yaml``, ``metrics.jsonl`` and ``last.pt`` (so ``detector train --resume``
    continues it), and each training's experiment config. The trainings restored."""
    rec, restored = study.record, []
    meta = read_study_record(rec)
    for name in meta.get("trainings", {}):
        t = by_name(name)
        src, dst = rec / "runs" / name, study.run(t)
        if dst.exists() or not (src / "config.yaml").is_file():
            continue
        for f in ("config.yaml", "metrics.jsonl", "done", "last.pt"):
            if (src / f).is_file() and not (src / f).is_symlink():
                write_bytes(dst / f, (src / f).read_bytes())
        if not study.config(t).is_file():
            write_text(study.config(t), yaml.safe_dump(study_config(t), sort_keys=False))
        restored.append(name)
    return restored


def record_has_test_of(study: Study, t: Training) -> bool:
    """Whether the record holds ``t``'s test results from an earlier session (its work folder is restored without
    them, and a finished training's ``last.pt`` is no longer in the record to test again)."""
    state = read_study_record(study.record).get("trainings", {}).get(t.name, {})
    return bool(state.get("tested")) and (study.record / "test" / t.name / "metrics.json").is_file()


def done_trainings(study: Study) -> set[str]:
    """Names of the trainings that are done in the work folder or in the record."""
    meta = read_study_record(study.record)
    recorded = {n for n, s in meta.get("trainings", {}).items() if s.get("status") == "done"}
    return recorded | {t.name for t in trainings() if study.done(t)}
