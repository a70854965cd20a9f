"""The accuracy study's analysis, from its record alone (no dataset, no weights): learning curves, test AP, the
sparse - dense gap with its 95 % interval (:mod:`detector.eval.bootstrap`), the ablations against the seed spread.

Writes the summary ``accuracy.json`` beside the record folder (:func:`reproduction.study.summary_path`:
docs/results-data/accuracy.json), and ``accuracy.md`` (the text docs/results.md shows in its "Accuracy" section) and
``curves.png`` (validation 3D and BEV AP per epoch) into the record. AP in percent, KITTI protocol Overall level R40
unless a key names the paper's Open3D-ML metric.

The summary's keys: ``splits`` (``train`` / ``val`` / ``test``: house ids), ``trainings`` (per training ``name``,
``model`` (``dense``, ``sparse`` or an ablation name), ``seed``, ``status``, ``epochs``, ``val_epochs``, ``val_ap_3d``
and ``val_ap_bev`` per epoch, ``ended_by``, ``decay_epochs``, and ``test``: its test AP, null until it is tested),
``gap_3d`` and ``gap_bev`` (the sparse - dense gap: ``mean``, ``ci95`` as ``[lo, hi]``, both null until a seed of each
model is tested; then also ``seeds``, ``frames``, ``resamples``, ``verdict`` ...), ``gap_open3d_ml_3d`` /
``gap_open3d_ml_bev`` where Open3D-ML loads, ``ablations`` against the dense seed spread once tested, ``schedule``,
``rule``, ``paper_gap_3d``, ``dataset_sha256`` and the record's ``notes``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from detector.eval.bootstrap import GapEstimate, bootstrap_gap, kitti_ap, open3d_ml_ap
from mpchair.core.errors import InputError
from mpchair.kitti import Labels, parse_labels
from mpchair.paper import MATTERPORT_CHAIR_AP
from reproduction.results import ABLATIONS, OPEN3D_ML_JSON
from reproduction.study import MODELS, STUDY_TRAIN, by_name, read_study_record, read_zip_texts, summary_path

#: The paper's sparse - dense 3D AP gap on Matterport-Chair (Open3D-ML mAP; mpchair.paper cites where).
PAPER_GAP_3D = MATTERPORT_CHAIR_AP.sparse_3d_delta
#: Bootstrap resamples of the test frames (per resample every tested seed of both models is evaluated). The KITTI
#: evaluator takes ~0.06 s for the 800 test frames, Open3D-ML's mAP (pure Python) ~2.9 s (a one-off timing loop on the
#: AVX2 EPYC, 2026-12-06, not a repository tool), so its gaps draw fewer.
RESAMPLES = 200
RESAMPLES_OPEN3D_ML = 40
CLASS = "Chair"
#: The gaps every summary holds (with a null ``mean`` / ``ci95`` until both models have a tested seed).
GAP_KEYS = ("gap_3d", "gap_bev")


@dataclass(frozen=True)
class Curve:
    """A training's validation curve: per evaluated epoch the 3D and BEV AP; ``end`` its end record (None: running)."""

    epochs: tuple[int, ...]
    ap_3d: tuple[float, ...]
    ap_bev: tuple[float, ...]
    end: dict | None


def read_curve(metrics: Path) -> Curve:
    """The validation curve in a run's metrics.jsonl."""
    epochs, ap3, apb, end = [], [], [], None
    for line in metrics.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(rec, dict):
            continue
        if rec.get("kind") == "eval" and CLASS in rec:
            epochs.append(int(rec["epoch"]))
            ap3.append(float(rec[CLASS]["3d"]["overall"]["R40"]))
            apb.append(float(rec[CLASS]["bev"]["overall"]["R40"]))
        elif rec.get("kind") == "end":
            end = rec
    return Curve(tuple(epochs), tuple(ap3), tuple(apb), end)


def _test_ap(folder: Path) -> dict:
    """A tested training's test AP: KITTI 3D / BEV (Overall R40) and Open3D-ML 3D / BEV."""
    out: dict = {}
    metrics = folder / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        result = m.get("result", m)
        if CLASS in result:
            out["ap_3d"] = float(result[CLASS]["3d"]["overall"]["R40"])
            out["ap_bev"] = float(result[CLASS]["bev"]["overall"]["R40"])
    o3d = folder / OPEN3D_ML_JSON
    if o3d.is_file():
        m = json.loads(o3d.read_text())
        if CLASS in m:
            out["open3d_ml_3d"], out["open3d_ml_bev"] = float(m[CLASS]["3d"]), float(m[CLASS]["bev"])
    return out


def _frames(zip_path: Path, ids: list[str], *, results: bool) -> list[Labels]:
    texts = read_zip_texts(zip_path)
    missing = [i for i in ids if i not in texts]
    if missing:
        raise InputError(f"no file for test frame {missing[0]}", zip_path)
    frames = [parse_labels(texts[i], f"{zip_path}:{i}.txt") for i in ids]
    if results:
        frames = [f if f.score is not None else Labels.empty(with_score=True) for f in frames]
    return frames


def gaps(record: Path, tested: dict[str, list[str]], resamples: int = RESAMPLES,
         resamples_open3d_ml: int = RESAMPLES_OPEN3D_ML) -> dict[str, GapEstimate]:
    """sparse - dense gaps (``3d``, ``bev``, ``open3d_ml_3d``, ``open3d_ml_bev`` where Open3D-ML loads) over the
    tested seeds ``tested[model]`` (training names), from the record's test detections and labels."""
    labels = read_zip_texts(record / "test_labels.zip")
    ids = sorted(labels)
    gt = [parse_labels(labels[i], f"{record / 'test_labels.zip'}:{i}.txt") for i in ids]
    dets = {m: [_frames(record / "test" / n / "detections.zip", ids, results=True) for n in tested[m]]
            for m in MODELS}
    fns = {"3d": kitti_ap(CLASS, "3d"), "bev": kitti_ap(CLASS, "bev")}
    try:
        from detector.eval.open3d_ml import load_open3d_ml_map

        load_open3d_ml_map()
        fns |= {"open3d_ml_3d": open3d_ml_ap(CLASS, "3d"), "open3d_ml_bev": open3d_ml_ap(CLASS, "bev")}
    except Exception:  # noqa: BLE001 (Open3D-ML is an optional extra: its gaps are then left out, and said so)
        pass
    return {k: bootstrap_gap(gt, dets["dense"], dets["sparse"], fn,
                             resamples=resamples_open3d_ml if k.startswith("open3d") else resamples)
            for k, fn in fns.items()}


def analyse(record: Path, resamples: int = RESAMPLES) -> dict:
    """The summary's data (accuracy.json, see the module docstring) from the record."""
    meta = read_study_record(record)
    trainings = []
    for name, state in sorted(meta.get("trainings", {}).items(), key=lambda kv: _order(kv[0])):
        metrics = record / "runs" / name / "metrics.jsonl"
        if not metrics.is_file():
            continue
        curve = read_curve(metrics)
        entry = {"name": name, "model": state.get("model"), "seed": state.get("seed"),
                 "status": state.get("status"), "epochs": len(curve.epochs), "val_epochs": list(curve.epochs),
                 "val_ap_3d": [round(x, 4) for x in curve.ap_3d], "val_ap_bev": [round(x, 4) for x in curve.ap_bev],
                 "ended_by": (curve.end or {}).get("reason"),
                 "decay_epochs": (curve.end or {}).get("decay_epochs")}
        entry["test"] = _test_ap(record / "test" / name) if state.get("tested") else None
        trainings.append(entry)
    tested = {m: [t["name"] for t in trainings if t["model"] == m and t["test"]] for m in MODELS}
    out: dict = {"splits": meta.get("split_houses"), "dataset_sha256": meta.get("dataset_sha256"),
                 "schedule": dict(STUDY_TRAIN), "trainings": trainings,
                 "rule": "plateau: best val 3D AP (Overall R40) of the last 5 epochs < 1.0 above the best before "
                         "them; first plateau: LR x 0.1, second: stop (cap 60 epochs)",
                 "paper_gap_3d": PAPER_GAP_3D, "notes": list(meta.get("notes", []))}
    for key in GAP_KEYS:  # the keys are there from the first training on; their figures once both models are tested
        out[key] = {"mean": None, "ci95": None,
                    "verdict": "not measured yet: it needs a tested seed of each model", "tested": tested}
    if all(tested[m] for m in MODELS) and (record / "test_labels.zip").is_file():
        previous = _previous_gaps(record, tested, resamples)
        if previous:  # the same tested seeds and resamples: the same numbers (the bootstrap is seeded), not redrawn
            out |= previous
        else:
            for key, g in gaps(record, tested, resamples, max(1, min(resamples, RESAMPLES_OPEN3D_ML))).items():
                out[f"gap_{key}"] = {**g.to_json(), "verdict": g.verdict(PAPER_GAP_3D), "tested": tested,
                                     "resamples_asked": resamples}
    spread = [t["test"]["ap_3d"] for t in trainings if t["model"] == "dense" and "ap_3d" in (t["test"] or {})]
    if spread:
        mean = sum(spread) / len(spread)
        out["ablations"] = [
            {"name": t["name"], "ap_3d": t["test"]["ap_3d"], "delta_to_dense_mean": t["test"]["ap_3d"] - mean,
             "dense_seed_range": [min(spread) - mean, max(spread) - mean]}
            for t in trainings if t["model"] in ABLATIONS and "ap_3d" in (t["test"] or {})]
    return out


def _previous_gaps(record: Path, tested: dict[str, list[str]], resamples: int) -> dict:
    """The gap entries of the record's summary (accuracy.json) when they were computed from these tested trainings
    with these resamples ({} otherwise)."""
    path = summary_path(record)
    if not path.is_file():
        return {}
    old = json.loads(path.read_text())
    entries = {k: v for k, v in old.items() if k.startswith("gap_") and isinstance(v, dict)}
    if entries and all(v.get("tested") == tested and v.get("resamples_asked") == resamples
                       and v.get("mean") is not None for v in entries.values()):
        # the verdict is worded from the stored interval each time, so a rewording reaches an old record's text
        return {k: {**v, "verdict": GapEstimate.from_json(v).verdict(PAPER_GAP_3D)} for k, v in entries.items()}
    return {}


def _order(name: str) -> int:
    from reproduction.study import trainings

    names = [t.name for t in trainings()]
    by_name(name)
    return names.index(name)


def _fmt(x: float | None) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2f}"


def markdown(data: dict) -> str:
    """accuracy.md: the study's state, its trainings and the gap with what its interval supports."""
    done = [t for t in data["trainings"] if t["status"] == "done"]
    lines = [f"Trainings in the record: {len(data['trainings'])} of 10 started, {len(done)} finished "
             "(3 seeds each of dense and sparse, one of each ablation; tools/accuracy_study.py).", ""]
    lines += [*(f"Note: {n}" for n in data.get("notes", [])), *([""] if data.get("notes") else [])]
    splits = data.get("splits") or {}
    if splits:
        lines += ["Houses per split: " + "; ".join(f"{k} {', '.join(splits[k])}" for k in ("train", "val", "test")
                                                   if k in splits) + ".", ""]
    if data["trainings"]:
        lines += ["| training | status | epochs | best val 3D AP | ended by | test 3D AP | test BEV AP |",
                  "|---|---|---|---|---|---|---|"]
    for t in data["trainings"]:
        best = max(t["val_ap_3d"]) if t["val_ap_3d"] else None
        test = t["test"] or {}
        lines.append(f"| {t['name']} | {t['status']} | {t['epochs']} | {_fmt(best)} | {t['ended_by'] or '–'} | "
                     f"{_fmt(test.get('ap_3d'))} | {_fmt(test.get('ap_bev'))} |")
    if data["trainings"]:
        lines.append("")
    g = data.get("gap_3d")
    if g is None or g.get("mean") is None:
        lines.append("Sparse - dense gap: not measured yet (it needs at least one tested seed of each model; the "
                     "interval needs three of each to hold the seed-to-seed spread).")
    else:
        for key, label in (("gap_3d", "3D AP (KITTI Overall R40)"), ("gap_bev", "BEV AP (KITTI Overall R40)"),
                           ("gap_open3d_ml_3d", "3D mAP (Open3D-ML, the paper's metric)")):
            if data.get(key, {}).get("mean") is not None:
                gk = data[key]
                lines.append(f"- Sparse - dense, {label}: {gk['mean']:+.2f}, 95 % interval "
                             f"[{gk['ci95'][0]:+.2f}, {gk['ci95'][1]:+.2f}] ({gk['seeds']['a']} dense x "
                             f"{gk['seeds']['b']} sparse seeds, {gk['resamples']} resamples of {gk['frames']} test "
                             f"frames): {gk['verdict']}.")
    return "\n".join(lines) + "\n"


#: One colour per model of the study (its seeds share it): dense, sparse, then the ablations (matplotlib's tab10).
MODEL_COLOURS = dict(zip((*MODELS, *ABLATIONS), ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple",
                                                 "tab:brown"), strict=True))


def seed_mean(curves: list[list[float]]) -> list[float]:
    """The per-epoch mean of a model's seed curves over the epochs every seed has reached (a mean over fewer seeds at
    later epochs would jump where a seed's curve ends)."""
    n = min(len(c) for c in curves)
    return [sum(c[i] for c in curves) / len(curves) for i in range(n)]


def plot_curves(data: dict, path: Path) -> None:
    """Validation AP per epoch of every training, 3D and BEV (KITTI Overall R40) side by side: one colour per model,
    each seed a thin line, the mean over a model's seeds a thick one where it has more than one. Written without a
    software tag, so the same data gives the same bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    from mpchair.core.atomic import atomic_open

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110, sharex=True)
    by_model: dict[str, list[dict]] = {}
    for t in data["trainings"]:
        if t["model"] in MODEL_COLOURS and t["val_ap_3d"]:
            by_model.setdefault(t["model"], []).append(t)
    for ax, key, what in ((axes[0], "val_ap_3d", "3D AP"), (axes[1], "val_ap_bev", "BEV AP")):
        for model, runs in by_model.items():
            colour = MODEL_COLOURS[model]
            for t in runs:
                ax.plot(t["val_epochs"], t[key], color=colour, lw=0.9, alpha=0.75, marker="o", ms=2)
            if len(runs) > 1:
                mean = seed_mean([t[key] for t in runs])
                ax.plot(runs[0]["val_epochs"][:len(mean)], mean, color=colour, lw=2.4)
        ax.set_xlabel("epoch")
        ax.set_ylabel(f"val {what}, Overall R40 (%)")
        ax.set_title(f"validation {what}")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    handles = [Line2D([], [], color=MODEL_COLOURS[m], lw=1.5,
                      label=f"{m} ({len(r)} seed{'s' if len(r) > 1 else ''}"
                            + ("; thick: their mean" if len(r) > 1 else "") + ")")
               for m, r in by_model.items()]
    if handles:
        axes[1].legend(handles=handles, loc="lower right", fontsize=8)
    fig.suptitle("Learning curves on the validation houses (house-disjoint split)")
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", metadata={"Software": None})
    plt.close(fig)


def write_analysis(record: Path, resamples: int = RESAMPLES) -> dict:
    """The summary (:func:`reproduction.study.summary_path`) and accuracy.md and curves.png into ``record``; returns
    the data."""
    from mpchair.core.atomic import write_text

    data = analyse(record, resamples)
    write_text(summary_path(record), json.dumps(data, indent=1, sort_keys=True) + "\n")
    write_text(record / "accuracy.md", markdown(data))
    if any(t["val_ap_3d"] for t in data["trainings"]):
        plot_curves(data, record / "curves.png")
    return data
