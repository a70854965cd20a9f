"""Draw ``docs/img/conventions.png``: one box seen from above in the sensor frame (axes, heading, yaw, corner
numbers), from its right side (corner heights), and from above in the KITTI rectified camera frame (bottom centre,
``rotation_y``, ``alpha``). Everything is computed with mpchair.geometry, so the figure shows what the code does.

Usage: ``python tools/draw_conventions.py [--out docs/img/conventions.png]``. Same inputs give the same bytes.
"""

from __future__ import annotations

import argparse
import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mpchair.core.atomic import write_bytes  # noqa: E402
from mpchair.geometry import box_corners, boxes_to_kitti_camera, make_tr_velo_to_cam, transform_points  # noqa: E402
from mpchair.kitti import Calib  # noqa: E402

BOX = np.array([[5.0, 1.5, 0.6, 3.0, 1.6, 1.2, math.radians(30)]])  # sensor frame: x, y, z, l, w, h, yaw
RED, GREEN, BLUE, PURPLE = "tab:red", "tab:green", "tab:blue", "purple"


def _calib() -> Calib:
    P = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam(),
                 Tr_imu_to_velo=np.eye(3, 4))  # fmt: skip


def _arrow(ax, start, vec, colour, label, offset=(0.0, 0.0), **kw):
    ax.annotate("", xy=(start[0] + vec[0], start[1] + vec[1]), xytext=start,
                arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 2})  # fmt: skip
    ax.text(start[0] + vec[0] * 1.08 + offset[0], start[1] + vec[1] * 1.08 + offset[1], label, color=colour,
            fontsize=10, fontweight="bold", ha="center", va="center", **kw)  # fmt: skip


def _polygon(ax, pts, labels, colour="black"):
    closed = np.vstack([pts, pts[:1]])
    ax.plot(closed[:, 0], closed[:, 1], color=colour, lw=1.6)
    centre = pts.mean(axis=0)
    for p, text in zip(pts, labels):
        d = (p - centre) / np.linalg.norm(p - centre)
        ax.text(*(p + d * 0.35), text, color="darkred", fontsize=10, fontweight="bold", ha="center", va="center")


def _frame(ax, title, xlabel, ylabel):
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)


def draw(out: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.6), gridspec_kw={"width_ratios": [1.0, 0.8, 1.0]})
    corners = box_corners(BOX)[0]  # (8,3) sensor frame
    cx, cy, cz, l, w, h, yaw = BOX[0]

    # (a) sensor frame from above: x forward drawn up the page, y left drawn to the left, z towards the viewer.
    ax = axes[0]
    top = lambda p: np.stack([-p[..., 1], p[..., 0]], axis=-1)  # (x, y) → page (right, up)  # noqa: E731
    _arrow(ax, (0, 0), top(np.array([2.0, 0])), RED, "x forward", offset=(0.0, 0.25))
    _arrow(ax, (0, 0), top(np.array([0, 2.0])), GREEN, "y left", offset=(-0.1, 0.3))
    ax.text(0.25, -0.45, "z up (towards you)", color=BLUE, fontsize=9, fontweight="bold")
    ax.plot([0], [0], "o", color=BLUE, ms=9, mfc="white", mew=2)
    ax.plot([0], [0], ".", color=BLUE, ms=5)
    _polygon(ax, top(corners[:4, :2]), [f"{i} | {i + 4}" for i in range(4)])
    c = top(np.array([cx, cy]))
    heading = np.array([math.cos(yaw), math.sin(yaw)])
    _arrow(ax, c, top(heading * 2.3), PURPLE, "heading (+l)", offset=(-0.2, 0.25))
    ax.plot(*zip(c, c + top(np.array([2.3, 0]))), color=PURPLE, ls="--", lw=1)
    arc = np.linspace(0, yaw, 30)
    ax.plot(*top(np.stack([cx + 1.4 * np.cos(arc), cy + 1.4 * np.sin(arc)], axis=1)).T, color=PURPLE, lw=1.2)
    ax.text(c[0] - 0.12, c[1] + 1.5, "yaw", color=PURPLE, fontsize=10, ha="right")
    ax.plot(*c, "o", color=PURPLE, ms=4)
    ax.text(c[0] + 0.2, c[1] - 0.3, "centre", fontsize=8)
    ax.text(-4.6, 2.9, "box [x, y, z, l, w, h, yaw]\ncorner 'i | i+4': bottom | top,\nCCW from front-right",
            fontsize=8, va="top")  # fmt: skip
    ax.set_xlim(-4.8, 2.2)
    ax.set_ylim(-1.0, 8.6)
    _frame(ax, "(a) sensor / KITTI LiDAR frame, from above\n(metres; yaw CCW about +z from +x)", "-y (m)", "x (m)")

    # (b) the same box from its right side: the heading points right, z up; corner i + 4 is above corner i.
    ax = axes[1]
    local = (corners[:, :2] - [cx, cy]) @ heading  # position along the heading
    for i, j in [(3, 0), (0, 4), (4, 7), (7, 3)]:
        ax.plot([local[i], local[j]], [corners[i, 2], corners[j, 2]], color="black", lw=1.6)
    for i, dx, dy in [(0, 0.25, -0.12), (3, -0.25, -0.12), (4, 0.25, 0.12), (7, -0.25, 0.12)]:
        ax.text(local[i] + dx, corners[i, 2] + dy, f"{i}", color="darkred", fontweight="bold", ha="center")
    ax.text(0, cz - h / 2 - 0.45, "(1, 2, 5, 6 hidden behind)", ha="center", fontsize=8)
    ax.plot([0], [cz], "o", color=PURPLE, ms=4)
    ax.text(0.1, cz + 0.08, "centre z", fontsize=8)
    ax.plot([-l / 2 - 0.6, l / 2 + 0.6], [0, 0], color="gray", lw=0.8)
    ax.text(l / 2 + 0.6, 0.05, "sensor z = 0", fontsize=8, ha="right", color="gray")
    _arrow(ax, (l / 2 + 0.3, cz), (0.9, 0.0), PURPLE, "heading", offset=(0.0, 0.2))
    ax.annotate("", xy=(-l / 2 - 0.3, cz + h / 2), xytext=(-l / 2 - 0.3, cz - h / 2),
                arrowprops={"arrowstyle": "<->", "lw": 1})  # fmt: skip
    ax.text(-l / 2 - 0.45, cz, "h", ha="right", va="center")
    ax.annotate("", xy=(l / 2, cz + h / 2 + 0.25), xytext=(-l / 2, cz + h / 2 + 0.25),
                arrowprops={"arrowstyle": "<->", "lw": 1})  # fmt: skip
    ax.text(0, cz + h / 2 + 0.35, "l", ha="center")
    ax.set_xlim(-2.6, 2.9)
    ax.set_ylim(-0.9, 2.2)
    _frame(ax, "(b) the box from its right side\n(front to the right; z up)", "along the heading (m)", "z (m)")

    # (c) rectified camera frame from above: x right, z forward drawn up the page, y down (away from you).
    calib = _calib()
    cam = transform_points(corners, calib.velo_to_rect())
    location, _, ry, alpha = boxes_to_kitti_camera(BOX, calib)
    ax = axes[2]
    xz = lambda p: np.stack([p[..., 0], p[..., 2]], axis=-1)  # noqa: E731
    _arrow(ax, (0, 0), (2.0, 0), RED, "x right", offset=(0.1, -0.3))
    _arrow(ax, (0, 0), (0, 2.0), BLUE, "z forward", offset=(0.0, 0.25))
    ax.plot([0], [0], "x", color=GREEN, ms=9, mew=2)
    ax.text(-0.3, -0.7, "y down (away from you)", color=GREEN, fontsize=9, fontweight="bold")
    _polygon(ax, xz(cam[:4]), [f"{i} | {i + 4}" for i in range(4)], colour="dimgray")
    loc = xz(location[0])
    ax.plot(*loc, "ko", ms=5)
    ax.text(loc[0] + 0.2, loc[1] - 0.45, "location\n(bottom centre)", fontsize=8)
    face = np.array([math.cos(ry[0]), -math.sin(ry[0])])  # heading in (x, z): rotation by ry about +y from +x
    _arrow(ax, loc, face * 2.3, PURPLE, "heading", offset=(-0.2, 0.25))
    ax.plot(*zip(loc, loc + [2.3, 0]), color=PURPLE, ls="--", lw=1)
    arc = np.linspace(0, ry[0], 40)
    ax.plot(loc[0] + 1.3 * np.cos(arc), loc[1] - 1.3 * np.sin(arc), color=PURPLE, lw=1.2)
    ax.text(loc[0] + 1.45, loc[1] + 0.95, f"rotation_y = -yaw - pi/2\n= {math.degrees(ry[0]):.0f} deg", fontsize=8,
            color=PURPLE)  # fmt: skip
    ax.plot([0, loc[0] * 1.15], [0, loc[1] * 1.15], color="gray", ls=":", lw=1)
    alpha_deg = math.degrees(alpha[0])
    ax.text(-4.6, 1.7, f"dotted: the ray, angle atan2(x, z)\nalpha = ry - atan2(x, z) = {alpha_deg:.1f} deg"
            "\nry > 0 turns clockwise seen\nfrom above (y points down)", fontsize=8, va="top")  # fmt: skip
    ax.set_xlim(-4.8, 2.2)
    ax.set_ylim(-1.0, 8.6)
    _frame(ax, "(c) KITTI rectified camera frame (labels), from above\n(metres; same box, R0_rect = I, pure axis "
           "swap)", "x (m)", "z (m)")  # fmt: skip

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, metadata={"Software": None})
    plt.close(fig)
    write_bytes(out, buf.getvalue())


def main() -> None:
    repo = Path(__file__).resolve().parent.parent
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=repo / "docs" / "img" / "conventions.png")
    draw(ap.parse_args().out)


if __name__ == "__main__":
    main()
