"""Formatting of evaluation results: a text table per class, or the JSON the CLI prints, for the KITTI protocol
(:class:`detector.eval.kitti.EvalResult`) and the reference's Open3D-ML metric
(:class:`detector.eval.open3d_ml.Open3DMLResult`)."""

from __future__ import annotations

import json

from detector.eval.kitti import LEVELS, METRICS, N_SAMPLE_PTS, EvalResult
from detector.eval.open3d_ml import O3D_METRICS, Open3DMLResult


def _count(n: int) -> str:
    return f"{str(n) + ('*' if n < N_SAMPLE_PTS else ''):>10}"


def format_table(result: EvalResult | Open3DMLResult) -> str:
    """KITTI: one block per class, num_gt, then AP (percent) per metric and variant (R40 first, the primary one) for
    Easy / Moderate / Hard / Overall; buckets with fewer than 41 valid GT are marked ``*`` (AP saturates below 100).
    Open3D-ML: one row per class with num_gt and its BEV and 3D mAP."""
    if isinstance(result, Open3DMLResult):
        return _format_open3d_ml(result)
    head = "".join(f"{d.capitalize():>10}" for d in LEVELS)
    lines = [f"KITTI evaluation, {result.num_frames} frames (AP in percent; R40 primary, R11 for comparison; "
             "Overall: every GT box of the class, no size / occlusion / truncation limit)"]
    for cls in result.classes:
        o = result.min_overlaps[cls]
        lines.append("")
        lines.append(f"{cls + f'  (IoU > bbox {o[0]:.2f}, bev {o[1]:.2f}, 3d {o[2]:.2f})':<52}{head}")
        counts = (*result.num_gt[cls], result.num_gt_overall[cls])
        lines.append(f"{'  num_gt (valid)':<52}" + "".join(_count(n) for n in counts))
        metrics = (*METRICS, "aos") if result.aos_computed else METRICS
        for m in metrics:
            for v in ("R40", "R11"):
                values = (*result.ap[cls][m][v], result.overall[cls][m][v])
                lines.append(f"{f'  {m:<5} AP_{v}':<52}" + "".join(f"{x:>10.2f}" for x in values))
        if not result.aos_computed:
            lines.append("  aos   off (no detections, or a detection with alpha = -10)")
    if result.warnings:
        lines.append("")
        lines.extend(f"warning: {w}" for w in result.warnings)
    return "\n".join(lines)


def _format_open3d_ml(result: Open3DMLResult) -> str:
    lines = [f"Open3D-ML mAP (the reference's metric), {result.num_frames} frames (AP in percent; every box "
             "difficulty 0, up to 41 sampled thresholds, IoU >= threshold)", "",
             f"{'class':<40}{'num_gt':>10}" + "".join(f"{m.upper() + ' AP':>10}" for m in O3D_METRICS)]
    for cls in result.classes:
        o = result.min_overlaps[cls]
        name = f"{cls}  (IoU >= bev {o[0]:.2f}, 3d {o[1]:.2f})"
        lines.append(f"{name:<40}{result.num_gt[cls]:>10}" + "".join(f"{result.ap[cls][m]:>10.2f}"
                                                                      for m in O3D_METRICS))
    if result.warnings:
        lines.append("")
        lines.extend(f"warning: {w}" for w in result.warnings)
    return "\n".join(lines)


def all_ap_zero(result: EvalResult | Open3DMLResult) -> bool:
    """Whether every AP of the result is 0 (every class, metric, recall variant and level): nothing was found."""
    if isinstance(result, Open3DMLResult):
        values = [v for cls in result.classes for v in result.ap[cls].values()]
    else:
        values = [x for cls in result.classes for m in result.ap[cls].values() for v in m.values() for x in v]
        values += [x for cls in result.classes for m in result.overall[cls].values() for x in m.values()]
    return all(v == 0 for v in values)


def to_json(result: EvalResult | Open3DMLResult) -> str:
    """The result's ``to_json_dict()``, indented. KITTI: ``{"<Class>": {"bbox"|"bev"|"3d"|"aos": {"R11": [e, m, h],
    "R40": [e, m, h], "overall": {"R11": x, "R40": y}}}, "num_gt": {...}, "num_gt_overall": {...}}`` (``aos`` null
    when AOS is off); Open3D-ML: ``{"protocol": "open3d-ml", "<Class>": {"bev": x, "3d": y}, "num_gt": {...}}``."""
    return json.dumps(result.to_json_dict(), indent=2)
