"""The KITTI object evaluation protocol (2D bbox, BEV, 3D, AOS; AP_R11 and AP_R40), reproduced rule for rule.

Follows the reference evaluators (devkit C++ ``evaluate_object.cpp``; OpenPCDet / mmdet3d / traveller59
``kitti_object_eval_python/eval.py``) as documented in ``docs/evaluation.md`` and
``kitti-format-and-eval.md`` section 4: difficulty flags with their ``<=`` / ``<`` asymmetries, neighbour classes,
pass 1 (highest score per GT in file order), ``get_thresholds`` (at most 41), pass 2 (highest IoU, ignored
fallback), strictly-greater IoU, DontCare suppression in 2D only, max-accumulated precision, few-GT saturation.
Besides Easy / Moderate / Hard it evaluates a fourth level, ``overall``: the same protocol with the 2D-height,
occlusion and truncation limits removed (every GT box of the class counts, no detection is ignored for its height).

One deliberate difference: BEV and 3D overlaps come from the exact float64 polygon clip of :mod:`detector.ops`
(identical rotated boxes score IoU 1), not the reference's float32 kernel that returns ~0 for them.

Frames: labels stay in the KITTI file frame — 2D boxes in image_2 pixels ``[left, top, right, bottom]``, 3D boxes
in the rectified camera frame (bottom centre, dims h w l, ry about +y).

Speed: per metric, every GT×detection overlap of every frame is computed once (flat pair list, numba kernel) and
shared by all classes, difficulties and score thresholds; matching runs in numba over flat per-frame offsets.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from detector.ops.iou import camera_boxes, camera_overlaps_indexed
from mpchair.core.jit import njit_cached
from mpchair.kitti import DONTCARE, Labels

DIFFICULTIES: tuple[str, ...] = ("easy", "moderate", "hard")
#: Every evaluation level: the three KITTI difficulties, then ``overall`` (every GT box of the class counts, no
#: detection is ignored for its 2D height: the single level of datasets without a difficulty split, such as the
#: paper's Matterport-Chair, whose reference marks every box difficulty 0).
LEVELS: tuple[str, ...] = (*DIFFICULTIES, "overall")
#: Per level: minimum 2D box height (px; a GT fails at ``height <= min``, a detection at ``height < min``),
#: maximum occlusion level and maximum truncation (a GT fails above them). ``overall`` has no limit (infinite
#: bounds, so the same comparisons never fail); DontCare and the neighbour classes act as at every level.
MIN_HEIGHT: tuple[float, ...] = (40.0, 25.0, 25.0, -math.inf)
MAX_OCCLUSION: tuple[float, ...] = (0, 1, 2, math.inf)
MAX_TRUNCATION: tuple[float, ...] = (0.15, 0.3, 0.5, math.inf)
#: Index of ``overall`` in :data:`LEVELS` and in the rows of ``EvalResult.precision``.
OVERALL = 3

METRICS: tuple[str, ...] = ("bbox", "bev", "3d")
#: AP variants: 11 recall points (0, 0.1, ..., 1) and 40 (1/40, ..., 1).
VARIANTS: tuple[str, ...] = ("R11", "R40")
#: Number of precision samples (threshold slots): recall 0, 1/40, ..., 1.
N_SAMPLE_PTS = 41

#: GT classes ignored (neither TP nor FN; a detection matched to one is no FP) when evaluating a class.
NEIGHBOURS: Mapping[str, tuple[str, ...]] = {"car": ("van",), "pedestrian": ("person_sitting",)}

#: Minimum overlaps (bbox, bev, 3d), the "strict" KITTI table plus Chair (kitti-format-and-eval.md 4.4).
#: Keys are lower case; classes are looked up case-insensitively.
DEFAULT_MIN_OVERLAPS: Mapping[str, tuple[float, float, float]] = {
    "car": (0.7, 0.7, 0.7),
    "pedestrian": (0.5, 0.5, 0.5),
    "cyclist": (0.5, 0.5, 0.5),
    "van": (0.7, 0.7, 0.7),
    "person_sitting": (0.5, 0.5, 0.5),
    "truck": (0.7, 0.7, 0.7),
    "chair": (0.5, 0.5, 0.5),
}

_INVALID_ALPHA = -10.0


@dataclasses.dataclass(frozen=True)
class EvalResult:
    """KITTI AP per class, metric, variant and level (percent, 0–100).

    ``ap[cls][metric][variant]`` is ``(easy, moderate, hard)`` with metric in ``bbox | bev | 3d | aos`` and variant
    ``R11 | R40``; ``overall[cls][metric][variant]`` is the ``overall`` level's AP (every GT box of the class counts,
    no detection is ignored for its 2D height). ``aos`` is absent when AOS is off (``aos_computed`` False: no
    detections, or a detection with alpha = -10). ``num_gt[cls]`` is num_valid_gt per difficulty,
    ``num_gt_overall[cls]`` at ``overall``. ``precision[cls][metric]`` is the (4, 41) max-accumulated precision
    (orientation similarity for ``aos``) per threshold slot, rows in :data:`LEVELS` order (easy, moderate, hard,
    overall). ``min_overlaps[cls]`` is (bbox, bev, 3d). ``warnings`` lists buckets with fewer than 41 valid GT (AP
    cannot reach 100 there).
    """

    classes: tuple[str, ...]
    min_overlaps: dict[str, tuple[float, float, float]]
    num_gt: dict[str, tuple[int, int, int]]
    ap: dict[str, dict[str, dict[str, tuple[float, float, float]]]]
    precision: dict[str, dict[str, np.ndarray]]
    aos_computed: bool
    num_frames: int
    overall: dict[str, dict[str, dict[str, float]]]
    num_gt_overall: dict[str, int]
    warnings: tuple[str, ...] = ()

    def to_json_dict(self) -> dict:
        """``{"<Class>": {"bbox"|"bev"|"3d"|"aos": {"R11": [e, m, h], "R40": [e, m, h], "overall": {"R11": x,
        "R40": y}}}, "num_gt": {"<Class>": [e, m, h]}, "num_gt_overall": {"<Class>": n}}``.

        ``aos`` is ``null`` when AOS is off.
        """
        out: dict = {}
        for cls in self.classes:
            metrics = (*METRICS, "aos") if self.aos_computed else METRICS
            entry: dict = {
                m: {**{v: list(self.ap[cls][m][v]) for v in VARIANTS}, "overall": dict(self.overall[cls][m])}
                for m in metrics
            }
            entry.setdefault("aos", None)
            out[cls] = entry
        out["num_gt"] = {cls: list(self.num_gt[cls]) for cls in self.classes}
        out["num_gt_overall"] = dict(self.num_gt_overall)
        return out


# --- matching kernels (numba) ----------------------------------------------------------------------------------------


@njit_cached
def _pass1(ov, ov_off, gt_off, dt_off, gt_flag, dt_flag, score, min_overlap):
    """TP scores over all frames: per GT in file order, the highest-scoring unassigned detection with IoU > thr.

    ``ov[ov_off[f] + j * ng + i]`` is the overlap of detection j and GT i of frame f. Flags: 0 valid, 1 ignored,
    -1 not this class. Ties in score keep the first detection (strict ``>``), as the reference.
    """
    out = np.empty(gt_flag.shape[0])
    n_out = 0
    max_nd = 0
    for f in range(gt_off.shape[0] - 1):
        max_nd = max(max_nd, dt_off[f + 1] - dt_off[f])
    assigned = np.zeros(max_nd, dtype=np.bool_)
    for f in range(gt_off.shape[0] - 1):
        g0 = gt_off[f]
        ng = gt_off[f + 1] - g0
        d0 = dt_off[f]
        nd = dt_off[f + 1] - d0
        o0 = ov_off[f]
        assigned[:nd] = False
        for i in range(ng):
            if gt_flag[g0 + i] == -1:
                continue
            det = -1
            best = -10000000.0  # the reference's NO_DETECTION sentinel doubles as the running best score
            for j in range(nd):
                if dt_flag[d0 + j] == -1 or assigned[j]:
                    continue
                if ov[o0 + j * ng + i] > min_overlap and score[d0 + j] > best:
                    det = j
                    best = score[d0 + j]
            if det < 0:
                continue
            assigned[det] = True
            if gt_flag[g0 + i] == 0 and dt_flag[d0 + det] == 0:
                out[n_out] = score[d0 + det]
                n_out += 1
    return out[:n_out]


@njit_cached
def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """Score thresholds at recall steps of ``1 / (num_sample_pts - 1)``, picked from the TP scores (reference rule).

    Scores are sorted descending; score i (recall ``l = (i+1)/num_gt``, next ``r = (i+2)/num_gt``, ``r = l`` for
    the last) is skipped when it is not the last and ``r - r* < r* - l`` (``r*`` the running recall target),
    else taken and ``r* += 1/40``. The last score is always taken; at most 41 are taken.
    """
    s = np.sort(scores)[::-1]
    n = s.shape[0]
    out = np.empty(n)
    k = 0
    current = 0.0
    for i in range(n):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < n - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < n - 1:
            continue
        out[k] = s[i]
        k += 1
        current += 1.0 / (num_sample_pts - 1.0)
    return out[:k]


@njit_cached
def _frame_stats(ov, o0, ng, nd, g0, d0, gt_flag, dt_flag, score, gt_alpha, dt_alpha, dt_bbox, dc_bbox, c0, nc,
                 use_dontcare, min_overlap, thr, compute_aos, assigned):
    """Pass 2 of one frame at score threshold ``thr``: (tp, fp, fn, orientation similarity)."""
    assigned[:nd] = False
    tp = 0
    fp = 0
    fn = 0
    sim = 0.0
    for i in range(ng):
        gf = gt_flag[g0 + i]
        if gf == -1:
            continue
        det = -1
        max_overlap = 0.0
        assigned_ignored = False
        for j in range(nd):
            df = dt_flag[d0 + j]
            if df == -1 or assigned[j] or score[d0 + j] < thr:
                continue
            o = ov[o0 + j * ng + i]
            if o > min_overlap and (o > max_overlap or assigned_ignored) and df == 0:
                # highest IoU among valid detections; a valid one replaces an ignored fallback
                max_overlap = o
                det = j
                assigned_ignored = False
            elif o > min_overlap and det == -1 and df == 1:
                # fallback: the first ignored (too small) detection, only while nothing else is found
                det = j
                assigned_ignored = True
        if det == -1:
            if gf == 0:
                fn += 1
        elif gf == 1 or dt_flag[d0 + det] == 1:
            assigned[det] = True
        else:
            tp += 1
            if compute_aos:
                sim += (1.0 + np.cos(gt_alpha[g0 + i] - dt_alpha[d0 + det])) / 2.0
            assigned[det] = True
    for j in range(nd):
        if not (assigned[j] or dt_flag[d0 + j] != 0 or score[d0 + j] < thr):
            fp += 1
    if use_dontcare:
        # 2D only: an unassigned valid detection whose intersection / own area with a DontCare box > thr is
        # taken off the FP count, once.
        nstuff = 0
        for c in range(c0, c0 + nc):
            for j in range(nd):
                if assigned[j] or dt_flag[d0 + j] != 0 or score[d0 + j] < thr:
                    continue
                b = dt_bbox[d0 + j]
                iw = min(b[2], dc_bbox[c, 2]) - max(b[0], dc_bbox[c, 0])
                if iw > 0:
                    ih = min(b[3], dc_bbox[c, 3]) - max(b[1], dc_bbox[c, 1])
                    if ih > 0:
                        if iw * ih / ((b[2] - b[0]) * (b[3] - b[1])) > min_overlap:
                            assigned[j] = True
                            nstuff += 1
        fp -= nstuff
    return tp, fp, fn, sim


@njit_cached
def _pass2(ov, ov_off, gt_off, dt_off, gt_flag, dt_flag, score, gt_alpha, dt_alpha, dt_bbox, dc_bbox, dc_off,
           use_dontcare, min_overlap, thresholds, compute_aos):
    """Summed (tp, fp, fn, similarity) per threshold over all frames (arrays of len(thresholds))."""
    nt = thresholds.shape[0]
    tp = np.zeros(nt, dtype=np.int64)
    fp = np.zeros(nt, dtype=np.int64)
    fn = np.zeros(nt, dtype=np.int64)
    sim = np.zeros(nt)
    max_nd = 0
    for f in range(gt_off.shape[0] - 1):
        max_nd = max(max_nd, dt_off[f + 1] - dt_off[f])
    assigned = np.zeros(max_nd, dtype=np.bool_)
    for f in range(gt_off.shape[0] - 1):
        g0 = gt_off[f]
        ng = gt_off[f + 1] - g0
        d0 = dt_off[f]
        nd = dt_off[f + 1] - d0
        relevant = False
        for i in range(ng):
            relevant = relevant or gt_flag[g0 + i] != -1
        for j in range(nd):
            relevant = relevant or dt_flag[d0 + j] == 0
        if not relevant:
            continue
        # Thresholds descend, so the set of detections with score >= t only grows: an unchanged count means an
        # unchanged set and the same frame result.
        prev_active = -1
        ftp, ffp, ffn, fsim = 0, 0, 0, 0.0
        for k in range(nt):
            active = 0
            for j in range(nd):
                if score[d0 + j] >= thresholds[k]:
                    active += 1
            if active != prev_active:
                ftp, ffp, ffn, fsim = _frame_stats(
                    ov, ov_off[f], ng, nd, g0, d0, gt_flag, dt_flag, score, gt_alpha, dt_alpha, dt_bbox, dc_bbox,
                    dc_off[f], dc_off[f + 1] - dc_off[f], use_dontcare, min_overlap, thresholds[k], compute_aos,
                    assigned)
                prev_active = active
            tp[k] += ftp
            fp[k] += ffp
            fn[k] += ffn
            sim[k] += fsim
    return tp, fp, fn, sim


# --- flags, overlaps, AP ---------------------------------------------------------------------------------------------


def gt_flags(names_lower: np.ndarray, bbox: np.ndarray, occluded: np.ndarray, truncated: np.ndarray, cls: str,
             difficulty: int) -> np.ndarray:
    """(G,) int64 GT flags for class ``cls`` (lower case) at level ``difficulty`` (index into :data:`LEVELS`:
    0 easy, 1 moderate, 2 hard, 3 overall, where nothing fails).

    0 valid (class ``cls`` passing the level); 1 ignored (a neighbour class, or ``cls`` failing the level: occluded
    > max, truncated > max, or 2D height ``<=`` min); -1 otherwise.
    """
    height = bbox[:, 3] - bbox[:, 1]
    is_cls = names_lower == cls
    neighbour = np.isin(names_lower, NEIGHBOURS.get(cls, ()))
    fails = (
        (occluded > MAX_OCCLUSION[difficulty])
        | (truncated > MAX_TRUNCATION[difficulty])
        | (height <= MIN_HEIGHT[difficulty])
    )
    flags = np.full(len(names_lower), -1, dtype=np.int64)
    flags[is_cls & ~fails] = 0
    flags[neighbour | (is_cls & fails)] = 1
    return flags


def dt_flags(names_lower: np.ndarray, bbox: np.ndarray, cls: str, difficulty: int) -> np.ndarray:
    """(D,) int64 detection flags: 1 (ignored) if ``|2D height| <`` min — tested first, for any class —, else 0 for
    class ``cls`` (lower case), else -1."""
    height = np.abs(bbox[:, 3] - bbox[:, 1])
    flags = np.where(names_lower == cls, 0, -1).astype(np.int64)
    flags[height < MIN_HEIGHT[difficulty]] = 1
    return flags


def _image_iou_pairs(dt: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(P,) axis-aligned IoU of pixel boxes (no +1), in the reference's operation order (dt area first)."""
    iw = np.minimum(dt[:, 2], gt[:, 2]) - np.maximum(dt[:, 0], gt[:, 0])
    ih = np.minimum(dt[:, 3], gt[:, 3]) - np.maximum(dt[:, 1], gt[:, 1])
    ok = (iw > 0) & (ih > 0)
    inter = iw * ih
    ua = (dt[:, 2] - dt[:, 0]) * (dt[:, 3] - dt[:, 1]) + (gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1]) - inter
    return np.divide(inter, ua, out=np.zeros_like(inter), where=ok)


def ap_r11(precision: np.ndarray) -> np.ndarray:
    """AP_R11 (percent) of (..., 41) max-accumulated precision: ``100/11 * sum(P[0::4])`` (reference order)."""
    total = np.zeros(precision.shape[:-1])
    for i in range(0, precision.shape[-1], 4):
        total = total + precision[..., i]
    return total / 11 * 100


def ap_r40(precision: np.ndarray) -> np.ndarray:
    """AP_R40 (percent) of (..., 41) max-accumulated precision: ``100/40 * sum(P[1:41])`` (recall 0 excluded)."""
    total = np.zeros(precision.shape[:-1])
    for i in range(1, precision.shape[-1]):
        total = total + precision[..., i]
    return total / 40 * 100


def _accumulate(values: np.ndarray, denominators: np.ndarray) -> np.ndarray:
    """(41,) ``values / denominators`` in the first len(values) slots (0 beyond, and where the denominator is 0),
    then max-accumulated from the right: ``P[i] = max(P[i:])``."""
    out = np.zeros(N_SAMPLE_PTS)
    n = len(values)
    # A threshold slot with TP + FP = 0 is possible only in contrived ignored-GT cases; the reference gets NaN there.
    out[:n] = np.divide(values, denominators, out=np.zeros(n), where=denominators > 0)
    return np.maximum.accumulate(out[::-1])[::-1]


@dataclasses.dataclass(frozen=True)
class _Flat:
    """All frames concatenated; ``*_off`` are (F+1,) offsets of frame f's rows."""

    gt_off: np.ndarray
    dt_off: np.ndarray
    ov_off: np.ndarray
    dc_off: np.ndarray
    gt_names: np.ndarray  # lower case
    gt_bbox: np.ndarray
    gt_occluded: np.ndarray
    gt_truncated: np.ndarray
    gt_alpha: np.ndarray
    dt_names: np.ndarray  # lower case
    dt_bbox: np.ndarray
    dt_alpha: np.ndarray
    dt_score: np.ndarray
    dc_bbox: np.ndarray
    overlaps: tuple[np.ndarray, np.ndarray, np.ndarray]  # bbox, bev, 3d over the flat (dt, gt) pair list


def _flatten(gt: Sequence[Labels], dt: Sequence[Labels]) -> _Flat:
    ng = np.array([len(g) for g in gt], dtype=np.int64)
    nd = np.array([len(d) for d in dt], dtype=np.int64)
    off = lambda n: np.concatenate([[0], np.cumsum(n)]).astype(np.int64)  # noqa: E731
    gt_off, dt_off, ov_off = off(ng), off(nd), off(ng * nd)

    def cat(frames: Sequence[Labels], field: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        parts = [getattr(f, field) for f in frames if len(f)]
        return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(shape, dtype=dtype)

    gt_raw = cat(gt, "names", (0,), str)
    gt_bbox = cat(gt, "bbox", (0, 4), np.float64)
    dt_bbox = cat(dt, "bbox", (0, 4), np.float64)
    gt_cam = camera_boxes(cat(gt, "location", (0, 3), np.float64), cat(gt, "dims_hwl", (0, 3), np.float64),
                          cat(gt, "rotation_y", (0,), np.float64))
    dt_cam = camera_boxes(cat(dt, "location", (0, 3), np.float64), cat(dt, "dims_hwl", (0, 3), np.float64),
                          cat(dt, "rotation_y", (0,), np.float64))
    is_dc = gt_raw == DONTCARE  # DontCare is matched by its exact name
    frame_of_gt = np.repeat(np.arange(len(gt)), ng)
    dc_off = off(np.bincount(frame_of_gt[is_dc], minlength=len(gt)))

    # Flat pair list, frame by frame, row-major (detection j, GT i): position ov_off[f] + j * ng[f] + i.
    counts = ng * nd
    frame = np.repeat(np.arange(len(gt)), counts)
    local = np.arange(int(counts.sum())) - np.repeat(ov_off[:-1], counts)
    j_local, i_local = np.divmod(local, np.maximum(ng[frame], 1))
    dt_idx = dt_off[frame] + j_local
    gt_idx = gt_off[frame] + i_local
    bev, d3 = camera_overlaps_indexed(dt_cam, gt_cam, dt_idx, gt_idx)
    return _Flat(
        gt_off=gt_off, dt_off=dt_off, ov_off=ov_off, dc_off=dc_off,
        gt_names=np.char.lower(gt_raw), gt_bbox=gt_bbox,
        gt_occluded=cat(gt, "occluded", (0,), np.int64),
        gt_truncated=cat(gt, "truncated", (0,), np.float64),
        gt_alpha=cat(gt, "alpha", (0,), np.float64),
        dt_names=np.char.lower(cat(dt, "names", (0,), str)), dt_bbox=dt_bbox,
        dt_alpha=cat(dt, "alpha", (0,), np.float64),
        dt_score=cat(dt, "score", (0,), np.float64),
        dc_bbox=np.ascontiguousarray(gt_bbox[is_dc]),
        overlaps=(_image_iou_pairs(dt_bbox[dt_idx], gt_bbox[gt_idx]), bev, d3),
    )


def resolve_min_overlaps(classes: Sequence[str], min_overlaps: Mapping[str, Sequence[float]] | None
                         ) -> dict[str, tuple[float, float, float]]:
    """``{class: (bbox, bev, 3d)}`` IoU thresholds for ``classes`` (spelled as given): :data:`DEFAULT_MIN_OVERLAPS`
    overridden or extended by ``min_overlaps`` (keys case-insensitive); ValueError for a bad value or unknown class."""
    table = dict(DEFAULT_MIN_OVERLAPS)
    for name, values in (min_overlaps or {}).items():
        v = tuple(float(x) for x in values)
        if len(v) != 3 or not all(0.0 <= x < 1.0 for x in v):
            raise ValueError(f"min overlaps for {name!r} must be three numbers in [0, 1) (bbox, bev, 3d), got {values}")
        table[name.lower()] = v
    out = {}
    for cls in classes:
        if cls.lower() not in table:
            raise ValueError(f"no IoU thresholds for class {cls!r}; known: {', '.join(sorted(table))} "
                             "(pass min_overlaps)")
        out[cls] = table[cls.lower()]
    return out


def check_inputs(gt: Sequence[Labels], dt: Sequence[Labels], classes: Sequence[str]) -> tuple[str, ...]:
    """``classes`` as a tuple, after checking that the frames pair up, detections have scores and no class repeats
    case-insensitively (ValueError otherwise)."""
    if len(gt) != len(dt):
        raise ValueError(f"{len(gt)} ground-truth frames but {len(dt)} detection frames")
    for f, d in enumerate(dt):
        if len(d) and d.score is None:
            raise ValueError(f"detections of frame {f} have no scores")
    classes = tuple(classes)
    if len({c.lower() for c in classes}) != len(classes):
        raise ValueError(f"classes repeat (case-insensitively): {classes}")
    return classes


def evaluate(
    gt: Sequence[Labels],
    dt: Sequence[Labels],
    classes: Sequence[str],
    min_overlaps: Mapping[str, Sequence[float]] | None = None,
) -> EvalResult:
    """Evaluate detections against ground truth with the KITTI protocol; AP in percent, at Easy / Moderate / Hard
    (``EvalResult.ap``) and at ``overall`` (``EvalResult.overall``: every GT box of the class counts).

    ``gt[f]`` / ``dt[f]`` are the labels of frame f (rectified camera frame, image_2 pixel boxes); detections need
    scores (an empty ``Labels`` may lack them). ``classes`` are matched case-insensitively against GT and detection
    names; the keys of the result are spelled as given. ``min_overlaps`` overrides or extends
    :data:`DEFAULT_MIN_OVERLAPS` with ``{class: (bbox, bev, 3d)}``. AOS is computed when there is at least one
    detection and none has alpha = -10 (the devkit's rule). A bucket with no valid GT gets AP 0.
    """
    classes = check_inputs(gt, dt, classes)
    thr_table = resolve_min_overlaps(classes, min_overlaps)
    flat = _flatten(gt, dt)
    compute_aos = len(flat.dt_alpha) > 0 and not np.any(flat.dt_alpha == _INVALID_ALPHA)

    num_gt: dict[str, tuple[int, int, int]] = {}
    num_gt_overall: dict[str, int] = {}
    ap: dict[str, dict[str, dict[str, tuple[float, float, float]]]] = {}
    overall: dict[str, dict[str, dict[str, float]]] = {}
    precision: dict[str, dict[str, np.ndarray]] = {}
    warnings: list[str] = []
    for cls in classes:
        key = cls.lower()
        prec = {m: np.zeros((len(LEVELS), N_SAMPLE_PTS)) for m in (*METRICS, "aos")}
        counts = []
        for d in range(len(LEVELS)):
            g_flag = gt_flags(flat.gt_names, flat.gt_bbox, flat.gt_occluded, flat.gt_truncated, key, d)
            d_flag = dt_flags(flat.dt_names, flat.dt_bbox, key, d)
            num_valid = int(np.count_nonzero(g_flag == 0))
            counts.append(num_valid)
            if num_valid < N_SAMPLE_PTS:
                warnings.append(
                    f"{cls} {LEVELS[d]}: {num_valid} valid GT (< {N_SAMPLE_PTS}); "
                    + ("AP is 0" if num_valid == 0 else "AP saturates below 100 even for perfect detections"))
            if num_valid == 0:
                continue  # every AP of this bucket stays 0, as the reference prints
            for m, metric in enumerate(METRICS):
                min_overlap = thr_table[cls][m]
                tp_scores = _pass1(flat.overlaps[m], flat.ov_off, flat.gt_off, flat.dt_off, g_flag, d_flag,
                                   flat.dt_score, min_overlap)
                thresholds = get_thresholds(tp_scores, num_valid)
                aos_here = compute_aos and m == 0  # AOS uses the 2D matching
                tp, fp, _fn, sim = _pass2(
                    flat.overlaps[m], flat.ov_off, flat.gt_off, flat.dt_off, g_flag, d_flag, flat.dt_score,
                    flat.gt_alpha, flat.dt_alpha, flat.dt_bbox, flat.dc_bbox, flat.dc_off, m == 0, min_overlap,
                    thresholds, aos_here)
                den = (tp + fp).astype(np.float64)
                prec[metric][d] = _accumulate(tp.astype(np.float64), den)
                if aos_here:
                    prec["aos"][d] = _accumulate(sim, den)
        num_gt[cls] = (counts[0], counts[1], counts[2])
        num_gt_overall[cls] = counts[OVERALL]
        used = (*METRICS, "aos") if compute_aos else METRICS
        precision[cls] = {m: prec[m] for m in used}
        curves = {m: {"R11": ap_r11(prec[m]), "R40": ap_r40(prec[m])} for m in used}
        ap[cls] = {m: {v: tuple(float(x) for x in curves[m][v][:OVERALL]) for v in VARIANTS} for m in used}
        overall[cls] = {m: {v: float(curves[m][v][OVERALL]) for v in VARIANTS} for m in used}
    return EvalResult(
        classes=classes, min_overlaps=thr_table, num_gt=num_gt, ap=ap, precision=precision,
        aos_computed=bool(compute_aos), num_frames=len(gt), overall=overall, num_gt_overall=num_gt_overall,
        warnings=tuple(warnings),
    )
