"""``tools/reproduce.py --weights committed``: the accuracy study's committed weights (``pretrained:dense`` /
``pretrained:sparse``, :mod:`detector.pretrained`) put where the reproduction's later steps read a training, and what
the run folder's ``done`` marker then says about where they came from.

The train step runs ``python -m reproduction.committed --model M --out RUN`` instead of ``detector train``; it writes
into ``RUN``:

    last.pt      the packed weights file itself (bf16 state dict + experiment config): every later step loads it
                 through detector.checkpoint exactly as ``--checkpoint pretrained:NAME`` does
    config.yaml  the experiment the weights were trained with (the one the file stores), as detector train writes it
    done         JSON: {"weights": "committed", "name", "sha256" (index.json's), "training" (the accuracy study's
                 training whose config the file stores, e.g. dense_s0), "epochs", "ended_by", "record"}

No metrics.jsonl: the trainings' logs are the accuracy study's (docs/results-data/accuracy/runs/<training>/).

Before anything is installed (and before ``tools/reproduce.py`` runs any step) the file index.json names for each
model is loaded (``torch.load(weights_only=True)``, detector.checkpoint) and its state dict's keys and shapes are
compared with the model the reproduction loads it into (``mpchair_<model>_cpu.yaml``): the SHA-256 only says the file
is the one the index lists, not that the index lists the right file (:func:`check_weights`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from mpchair.core.atomic import write_bytes, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from reproduction.checkout import ROOT
from reproduction.results import MODELS, epoch_records, read_text
from reproduction.scales import SCALES, Scale

#: ``--weights``: train the models here (``make reproduce``) or take the accuracy study's committed ones.
WEIGHTS = ("train", "committed")
#: The packaged name of each model's committed weights (the bench times ``mpchair_sparse_exact`` with the sparse
#: file, which index.json lists as ``sparse_exact`` too).
COMMITTED = {"dense": "dense", "sparse": "sparse"}
#: The accuracy study's record (tools/accuracy_study.py): the trainings the committed weights were packed from.
STUDY_RECORD = ROOT / "docs" / "results-data" / "accuracy"
#: The report section that shows the study's results (reproduction.report.accuracy_section).
STUDY_SECTION = "Accuracy: house-disjoint splits, plateau-trained seeds, an interval"
#: The seed of the study's dataset (reproduction.study.Study.plan: the full scale's synth / generate at seed 0).
STUDY_SEED = 0


@dataclasses.dataclass(frozen=True)
class CommittedWeights:
    """Where a run folder's committed weights came from: the packaged ``name`` and its file's ``sha256`` (index.json),
    the accuracy-study ``training`` whose config the file stores (None: not in the study's record), its finished
    ``epochs`` and what ended it (``ended_by``: plateau / cap; None while unfinished), the study's ``record``."""

    name: str
    sha256: str
    training: str | None = None
    epochs: int | None = None
    ended_by: str | None = None
    record: str = "docs/results-data/accuracy"

    def to_json(self) -> dict:
        return {"weights": "committed", **dataclasses.asdict(self)}

    @classmethod
    def from_json(cls, d: dict, source: Path) -> CommittedWeights:
        fields = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d.get("name"), str) or not isinstance(d.get("sha256"), str) or set(d) - fields - {"weights"}:
            raise InputError(f"not a committed-weights marker (expected {', '.join(sorted(fields))})", source)
        return cls(**{k: v for k, v in d.items() if k in fields})

    def text(self) -> str:
        """"pretrained:dense (dense_s0, 21 epochs, ended by plateau; sha256 65c49d4c5622)"."""
        origin = self.training or "training not found in the study's record"
        if self.epochs is not None:
            origin += f", {self.epochs} epochs" + (f", ended by {self.ended_by}" if self.ended_by else ", unfinished")
        return f"pretrained:{self.name} ({origin}; sha256 {self.sha256[:12]})"


def read_committed(run: Path) -> CommittedWeights | None:
    """The committed weights run folder ``run`` holds, from its ``done`` marker (None: trained here, or not yet)."""
    text = read_text(run / "done")
    if not text or not text.lstrip().startswith("{"):
        return None  # "trained": detector train's own run
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"not a committed-weights marker ({e})", run / "done") from None
    return CommittedWeights.from_json(d, run / "done") if isinstance(d, dict) and d.get("weights") == "committed" \
        else None


def weights_text(committed: dict[str, CommittedWeights]) -> str:
    """"pretrained:dense (dense_s0, 21 epochs, ended by plateau; sha256 65c49d4c5622) / pretrained:sparse (...)"."""
    return " / ".join(w.text() for w in committed.values())


def committed_runs(out: Path) -> dict[str, CommittedWeights]:
    """The models of work folder ``out`` whose runs hold committed weights, by model."""
    return {m: w for m in MODELS if (w := read_committed(out / "runs" / m)) is not None}


def model_config(model: str) -> Path:
    """The experiment config the reproduction's eval step loads model ``model``'s weights with
    (``detector/configs/mpchair_<model>_cpu.yaml``, as :func:`reproduction.steps.run_eval`)."""
    from detector.config import CONFIG_DIR

    return CONFIG_DIR / f"mpchair_{model}_cpu.yaml"


def check_weights(model: str, path: Path, weights: dict | None = None) -> None:
    """An :class:`InputError` (one line naming ``path`` and its ``pretrained:`` name) unless the committed weights
    file ``path`` holds model ``model``'s state dict: the keys and tensor shapes of the model :func:`model_config`
    builds (dense and sparse differ in both). ``weights``: the file's state dict when the caller has loaded it."""
    import torch

    from detector.checkpoint import load_checkpoint, weights_misfit
    from detector.config import load_experiment
    from detector.models import build_model
    from detector.pretrained import PREFIX

    if weights is None:
        weights = load_checkpoint(path).model  # torch.load(weights_only=True): nothing in the file runs
    config = model_config(model)
    with torch.device("meta"):  # keys and shapes only: no memory, no draw from the RNG
        reference = build_model(load_experiment(config).model)
    misfit = weights_misfit(reference, weights)
    if misfit is not None:
        raise InputError(f"{PREFIX}{COMMITTED[model]} is not the {model} model index.json lists it as: its weights do "
                         f"not fit the model {config.name} builds ({misfit}); nothing installed: pack the accuracy "
                         f"study's {model}_s0 under that name again (tools/pack_pretrained.py), or run with --weights "
                         "train", path)


def check_committed(folder: Path | None = None) -> dict[str, str]:
    """{model: sha256} of each model's committed weights in ``folder`` (default the package's detector/pretrained),
    checked against index.json and against the model (:func:`check_weights`); a name the index lacks is an
    :class:`InputError` saying how to make it."""
    from detector.pretrained import PREFIX, PRETRAINED_DIR, read_index, resolve_checkpoint

    index = read_index(folder)
    for model, name in COMMITTED.items():
        if name not in index:
            where = folder or PRETRAINED_DIR
            raise InputError(f"--weights committed: no committed weights {PREFIX}{name} in {where} (index.json lists "
                             f"{', '.join(sorted(index)) or 'none'}): pack the accuracy study's {model}_s0 once it "
                             f"has trained (tools/pack_pretrained.py RUN/last.pt --name {name}=mpchair_{model}_cpu"
                             + (" --name sparse_exact=mpchair_sparse_exact_cpu" if model == "sparse" else "")
                             + "), or run with --weights train")
        # the file is there and its sha256 is index.json's; then that it is the model it is listed as
        check_weights(model, resolve_checkpoint(PREFIX + name, folder))
    return {m: index[n].sha256 for m, n in COMMITTED.items()}


def install_text(model: str, run: Path, folder: Path | None = None) -> str:
    """The dry run's line for model ``model``'s train step under ``--weights committed``: which packed file it would
    put into run folder ``run`` (``folder``: the packed weights', default the package's), in place of a training."""
    from detector.pretrained import PREFIX, read_index

    name = COMMITTED[model]
    entry = read_index(folder).get(name)
    what = f" ({entry.file}, sha256 {entry.sha256[:12]})" if entry else " (not in index.json: the run would stop here)"
    return f"[train] {model}: no training; would install {PREFIX}{name}{what} into {run}/ (last.pt, config.yaml, done)"


def study_dataset_problem(sc: Scale, seed: int) -> str | None:
    """Why a run of scale ``sc`` and ``seed`` does not make the dataset the committed weights were trained on (the
    accuracy study's: the full scale's houses, frames and house split at seed 0), or None when it does."""
    study = SCALES["full"]
    want = (study.houses, study.frames_per_house, study.split_mode, STUDY_SEED)
    got = (sc.houses, sc.frames_per_house, sc.split_mode, seed)
    if got == want:
        return None
    return (f"--weights committed: the committed weights were trained on the accuracy study's dataset ({want[0]} "
            f"houses x {want[1]} frames split by {want[2]}, seed {want[3]}: --scale full or recipe), but this run's "
            f"is {got[0]} houses x {got[1]} frames split by {got[2]}, seed {got[3]}; its val / test frames would not "
            "be the ones the weights were never trained on. Use --scale full or recipe, or --weights train")


def folder_conflict(out: Path, weights: str, shas: dict[str, str] | None) -> str | None:
    """Why work folder ``out``'s runs do not hold what ``weights`` asks for (``shas``: the committed files' sha256
    by model), so that the skipped steps would time other weights: a training of this folder or a cut one under
    ``--weights committed``, other committed files, or committed weights under ``--weights train``; None if none."""
    for m in MODELS:
        run = out / "runs" / m
        held = read_committed(run)
        if weights == "train" and held is not None:
            return (f"{run} holds the committed weights {held.text()}, not a training of this run: run with "
                    "--weights committed, or --force to train here")
        if weights == "committed" and held is None and ((run / "done").exists() or (run / "last.pt").exists()):
            what = "a training of this run" if (run / "done").exists() else "a cut training (last.pt, no done)"
            return (f"{run} holds {what}, not the committed weights: use another --out, or --force to replace it "
                    "(and redo every step after it)")
        if weights == "committed" and held is not None and shas is not None and held.sha256 != shas[m]:
            return (f"{run} holds other committed weights ({held.text()}) than detector/pretrained's now (sha256 "
                    f"{shas[m][:12]}): use another --out, or --force to redo every step with the new ones")
    return None


def study_training(config: dict, record: Path = STUDY_RECORD) -> tuple[str, int | None, str | None] | None:
    """(name, finished epochs, what ended it) of the accuracy-study training in ``record`` whose ``config.yaml`` is
    the experiment ``config`` (a weights file's); None when none is (the study's seeds differ by ``train.seed``)."""
    from detector.config import experiment_from_dict
    from reproduction.results import end_record, read_run_config

    want = experiment_from_dict(config)
    runs = record / "runs"
    for run in sorted(p for p in runs.iterdir() if p.is_dir()) if runs.is_dir() else ():
        if read_run_config(run) == want:
            end = end_record(run)
            return run.name, len(epoch_records(run)) or None, end.get("reason") if end else None
    return None


def install(run: Path, model: str, folder: Path | None = None, record: Path = STUDY_RECORD) -> CommittedWeights:
    """Put model ``model``'s committed weights (from ``folder``, default the package's) into run folder ``run``:
    ``last.pt``, ``config.yaml`` and the ``done`` marker (module docstring); nothing for a file that is not that
    model's (:func:`check_weights`)."""
    from detector.checkpoint import load_checkpoint
    from detector.pretrained import PREFIX, read_index, resolve_checkpoint

    name = COMMITTED[model]
    path = resolve_checkpoint(PREFIX + name, folder)  # checked against index.json's sha256
    saved = load_checkpoint(path)
    if saved.config is None:
        raise InputError("the packed weights hold no experiment config; pack a detector train run's last.pt", path)
    check_weights(model, path, saved.model)  # before the first file is written
    import yaml

    # the file's bytes unchanged: last.pt then loads (bf16 tensors upcast by load_state_dict) as pretrained:NAME does
    write_bytes(run / "last.pt", path.read_bytes())
    write_text(run / "config.yaml", yaml.safe_dump(saved.config, sort_keys=False))  # as detector train writes it
    found = study_training(saved.config, record)
    weights = CommittedWeights(name=name, sha256=read_index(folder)[name].sha256,
                               **(dict(zip(("training", "epochs", "ended_by"), found)) if found else {}),
                               record=_relative(record))
    write_text(run / "done", json.dumps(weights.to_json(), indent=1) + "\n")  # last: it marks the step done
    return weights


def _relative(path: Path) -> str:
    """``path`` relative to the checkout where it lies inside it (the record's paths read the same everywhere)."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> int:
    """``python -m reproduction.committed --model M --out RUN [--pretrained DIR]``: the train step of ``--weights
    committed`` for one model; 2 with one ``error:`` line for weights that are not there."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", choices=MODELS, required=True)
    p.add_argument("--out", type=Path, required=True, help="the run folder (runs/<model>)")
    p.add_argument("--pretrained", type=Path, default=None,
                   help="folder of the packed weights and index.json (default: the package's detector/pretrained)")
    args = p.parse_args(argv)

    def work() -> int:
        weights = install(args.out, args.model, args.pretrained)
        print(f"[train] {args.model}: no training, the committed weights {weights.text()} in {args.out}")
        return 0

    return run_script(work)


if __name__ == "__main__":
    raise SystemExit(main())
