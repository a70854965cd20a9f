"""Formatting of :class:`detector.eval.kitti.EvalResult`: a text table per class, or the JSON the CLI prints."""

from __future__ import annotations

import json

from detector.eval.kitti import DIFFICULTIES, METRICS, N_SAMPLE_PTS, EvalResult


def format_table(result: EvalResult) -> str:
    """One block per class: num_gt, then AP (percent) per metric and variant (R40 first, the primary one) for
    Easy / Moderate / Hard. Buckets with fewer than 41 valid GT are marked ``*`` (AP saturates below 100)."""
    head = "".join(f"{d.capitalize():>10}" for d in DIFFICULTIES)
    lines = [f"KITTI evaluation, {result.num_frames} frames (AP in percent; R40 primary, R11 for comparison)"]
    for cls in result.classes:
        o = result.min_overlaps[cls]
        lines.append("")
        lines.append(f"{cls + f'  (IoU > bbox {o[0]:.2f}, bev {o[1]:.2f}, 3d {o[2]:.2f})':<52}{head}")
        counts = result.num_gt[cls]
        lines.append(f"{'  num_gt (valid)':<52}"
                     + "".join(f"{str(n) + ('*' if n < N_SAMPLE_PTS else ''):>10}" for n in counts))
        metrics = (*METRICS, "aos") if result.aos_computed else METRICS
        for m in metrics:
            for v in ("R40", "R11"):
                values = result.ap[cls][m][v]
                lines.append(f"{f'  {m:<5} AP_{v}':<52}" + "".join(f"{x:>10.2f}" for x in values))
        if not result.aos_computed:
            lines.append("  aos   off (no detections, or a detection with alpha = -10)")
    if result.warnings:
        lines.append("")
        lines.extend(f"warning: {w}" for w in result.warnings)
    return "\n".join(lines)


def to_json(result: EvalResult) -> str:
    """``{"<Class>": {"bbox"|"bev"|"3d"|"aos": {"R11": [e, m, h], "R40": [e, m, h]}}, "num_gt": {...}}`` (indented;
    ``aos`` is null when AOS is off)."""
    return json.dumps(result.to_json_dict(), indent=2)
