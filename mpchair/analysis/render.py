"""Pictures, all written as PNG files headless (no display needed): statistics plots, a frame's bird's-eye view, a
frame's 3D view and a house's top-down view.

* Matplotlib pictures use the object-oriented API (:class:`matplotlib.figure.Figure` + the Agg canvas), never
  ``pyplot``, so nothing depends on a GUI backend or on global figure state.
* The 3D view uses pyvista/VTK off-screen. Without a display VTK is asked for its EGL window (VTK 9.4+ reads
  ``VTK_DEFAULT_OPENGL_WINDOW``; set it yourself to pick another, e.g. ``vtkOSOpenGLRenderWindow``). When no
  off-screen OpenGL context can be made, :func:`render_frame_3d` raises :class:`RenderError` with the reason.
* Every file goes through :func:`mpchair.core.atomic.atomic_open`: a reader never sees a half-written PNG.

Frames: scans and boxes are in the sensor frame (x forward, y left, z up, metres; boxes ``(N, 7)`` ``[x, y, z, l, w,
h, yaw]`` geometric centre, yaw CCW about +z); houses and viewpoints in the Matterport world frame (z up, metres).
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError
from mpchair.geometry import BOX_EDGES, bev_polygons, box_corners, labels_to_boxes, yaw_of
from mpchair.kitti import Calib, frame_paths, read_calib, read_labels

#: Colours (matplotlib names / hex): ground truth, detections, highlighted objects, viewpoints.
GT_COLOUR = "#00b050"
DET_COLOUR = "#e8242b"
HIGHLIGHT_COLOUR = "#ff7f0e"
VIEWPOINT_COLOUR = "#1f4fff"
#: Metres below a level's bbox bottom where that level starts (its floor slab may sit slightly below the bbox).
LEVEL_MARGIN = 0.25


class RenderError(RuntimeError):
    """A picture could not be made on this machine (e.g. no off-screen OpenGL for the 3D view)."""


def _figure(size: tuple[int, int], dpi: int = 100):
    """A matplotlib Figure of exactly ``size = (W, H)`` pixels with an Agg canvas (no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _save_figure(fig, out: str | Path) -> None:
    """Write ``fig`` as a PNG of its exact pixel size (no tight bbox, which would change the size)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=fig.dpi)
    with atomic_open(out, "wb") as f:
        f.write(buf.getvalue())


def _save_rgb(image: np.ndarray, out: str | Path) -> None:
    """Write an (H, W, 3|4) uint8 array as a PNG."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG")
    with atomic_open(out, "wb") as f:
        f.write(buf.getvalue())


# ----------------------------------------------------------------------------------------------------------- plots


def plot_density_histogram(stats: dict, out: str | Path, size: tuple[int, int] = (900, 500)) -> None:
    """Histogram of per-frame density ``D`` (from :func:`mpchair.analysis.stats.density_stats`) with this dataset's
    median and the paper's medians (Matterport-Chair, KITTI: ``mpchair.paper``) marked; PNG of ``size = (W, H)`` pixels.
    """
    d = np.asarray([f["density"] for f in stats["frames"]], dtype=np.float64)
    paper = stats["paper"]
    fig = _figure(size)
    ax = fig.add_subplot(1, 1, 1)
    hi = max(float(d.max()), paper["kitti"]["max"]) * 1.05
    ax.hist(d, bins=np.linspace(0.0, hi, 41), color="#4c72b0", edgecolor="white", label=f"{len(d)} frames")
    ax.axvline(stats["median"], color="black", lw=2, label=f"this dataset: median {stats['median']:.5f}")
    styles = (("matterport_chair", "Matterport-Chair", "#dd8452"), ("kitti", "KITTI", "#55a868"))
    for key, name, colour in styles:
        ax.axvline(paper[key]["median"], color=colour, lw=2, ls="--", label=f"paper {name}: median "
                   f"{paper[key]['median']:.5f}")
        ax.axvspan(paper[key]["min"], paper[key]["max"], color=colour, alpha=0.12,
                   label=f"paper {name}: min-max {paper[key]['min']:.5f}-{paper[key]['max']:.5f}")
    g = stats["geometry"]
    # the grid as the docs and the configs' output_shape write it: [ny, nx] = 768 x 512 (geometry's grid is (nx, ny))
    ax.set_xlabel(f"pseudoimage density D = non-empty pillars / ({g['grid'][1]} x {g['grid'][0]} cells)")
    ax.set_ylabel("frames")
    ax.set_title(f"{Path(stats['dataset']).name or stats['dataset']}: density per frame"
                 + ("  (FOV-cropped)" if stats["fov_crop"] else "") + "  (shaded: paper min-max)")
    # beside the plot, not over it: inside, it covered the KITTI median line
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    fig.subplots_adjust(left=0.07, right=0.6, bottom=0.12, top=0.92)
    _save_figure(fig, out)


def _class_colours(names: Sequence[str]) -> dict[str, tuple]:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {n: cmap(i % 10) for i, n in enumerate(names)}


#: Colours of the l, w and h histograms of a one-class dataset (matplotlib's tab10 blue, orange, green).
DIMENSION_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c")


def plot_box_stats(stats: dict, out: str | Path, size: tuple[int, int] = (1600, 800)) -> None:
    """Multi-panel figure of :func:`mpchair.analysis.stats.box_stats`: boxes per frame, ``l / w / h`` (solid / dashed /
    dotted), points per box, distance, yaw, occlusion, truncation and, when the dataset has a manifest, rejected-box
    reasons; one colour per class, the mean box (anchor) per class in a text panel. Drawn from the histograms in
    ``stats`` alone, so a saved ``--json`` redraws the same figure.
    """
    classes = stats["classes"]
    colours = _class_colours(list(classes))
    fig = _figure(size)
    axes = fig.subplots(2, 4).reshape(-1)

    bpf = stats["boxes_per_frame"]["histogram"]
    axes[0].bar([int(k) for k in bpf], list(bpf.values()), color="#4c72b0")
    axes[0].set_title(f"boxes per frame ({stats['frames']} frames)")
    axes[0].set_xlabel("boxes in the frame")
    axes[0].set_ylabel("frames")

    def steps(ax, key: str, title: str, log: bool = False, ls: str = "-", label: bool = True) -> None:
        for name, c in classes.items():
            h = c[key]["histogram"]
            ax.stairs(h["counts"], h["edges"], color=colours[name], lw=2, ls=ls,
                      label=f"{name} ({c['count']})" if label else None)
        if log:
            ax.set_xscale("symlog", linthresh=1.0)
        ax.set_title(title)

    if len(classes) == 1:
        # one class: l, w and h overlap on one axis, so each gets its own colour (and its own legend entry)
        ((name, c),) = classes.items()
        for key, colour in zip(("l", "w", "h"), DIMENSION_COLOURS):
            h = c[key]["histogram"]
            axes[1].stairs(h["counts"], h["edges"], color=colour, lw=2, label=f"{key} ({name}, {c['count']})")
        axes[1].set_title("box size l, w, h [m]")
    else:
        for key, ls in (("l", "-"), ("w", "--"), ("h", ":")):
            steps(axes[1], key, "l (solid), w (dashed), h (dotted) [m]", ls=ls, label=key == "l")
    axes[1].legend(fontsize=7)
    steps(axes[2], "points", "points per box (log)", log=True)
    steps(axes[3], "distance", "centre distance hypot(x, y) [m]")
    steps(axes[4], "yaw", "yaw (sensor frame, CCW) [rad]")
    levels = sorted({int(k) for c in classes.values() for k in c["occluded"]})
    width = 0.8 / max(1, len(classes))
    for i, (name, c) in enumerate(classes.items()):
        axes[5].bar([lv + i * width for lv in levels], [c["occluded"].get(str(lv), 0) for lv in levels], width,
                    color=colours[name])
    axes[5].set_xticks([lv + 0.4 - width / 2 for lv in levels], [str(lv) for lv in levels])
    axes[5].set_title("occlusion level (label_2)")
    steps(axes[6], "truncated", "truncation (label_2)")
    for a in axes[1:7]:
        a.set_ylabel("boxes")
    ax = axes[7]
    rej = stats.get("rejected")
    # Text panel: the per-class mean box (the anchor a model config should use) and the manifest's reasons.
    text = ["mean box l x w x h [m]:"]
    text += [f"  {n} ({c['count']}): {c['l']['mean']:.3f} x {c['w']['mean']:.3f} x {c['h']['mean']:.3f}"
             for n, c in classes.items()]
    if rej:
        text += ["", f"rejected boxes ({sum(rej.values())}):"] + [f"  {k}: {v}" for k, v in list(rej.items())[:12]]
    else:
        text += ["", "no manifest.json (no rejected-box reasons)"]
    ax.text(0.0, 1.0, "\n".join(text), va="top", ha="left", family="monospace", fontsize=8, transform=ax.transAxes)
    ax.set_axis_off()
    fig.suptitle(f"{Path(stats['dataset']).name or stats['dataset']}: box statistics")
    # Fixed margins instead of tight_layout: measuring every label of 8 panels costs seconds.
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.08, top=0.9, wspace=0.3, hspace=0.4)
    _save_figure(fig, out)


# -------------------------------------------------------------------------------------------------------- frames


def _auto_extent(points: np.ndarray, boxes: Sequence[np.ndarray]) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` covering 99% of the points (robust to stray far returns) and every box."""
    xs, ys = [], []
    if len(points):
        lo = np.percentile(points[:, :2], 0.5, axis=0)
        hi = np.percentile(points[:, :2], 99.5, axis=0)
        xs += [lo[0], hi[0]]
        ys += [lo[1], hi[1]]
    for b in boxes:
        if len(b):
            poly = bev_polygons(b).reshape(-1, 2)
            xs += [poly[:, 0].min(), poly[:, 0].max()]
            ys += [poly[:, 1].min(), poly[:, 1].max()]
    xs.append(0.0)  # the sensor is always in view
    ys.append(0.0)
    margin = 0.05 * max(max(xs) - min(xs), max(ys) - min(ys), 1.0)
    return min(xs) - margin, max(xs) + margin, min(ys) - margin, max(ys) + margin


def label_anchors(boxes: np.ndarray) -> np.ndarray:
    """(N, 2) sensor-frame points (x, y, metres) where BEV labels of ``boxes`` (N, 7) sit: each box's corner with
    the largest y (the top of the picture), a corner of the box itself."""
    polys = bev_polygons(boxes)
    return polys[np.arange(len(polys)), np.argmax(polys[:, :, 1], axis=1)]


def _draw_bev_boxes(ax, boxes: np.ndarray, colour: str, texts: Sequence[str] | None, dashed: bool = False) -> None:
    from matplotlib.collections import LineCollection, PolyCollection

    if len(boxes) == 0:
        return
    polys = bev_polygons(boxes)
    ax.add_collection(PolyCollection(polys, facecolors="none", edgecolors=colour, linewidths=1.6,
                                     linestyles="--" if dashed else "-", zorder=3), autolim=False)
    # Heading: from the centre to the middle of the front edge (corners 0 and 1 are front-right / front-left).
    front = 0.5 * (polys[:, 0] + polys[:, 1])
    ax.add_collection(LineCollection(np.stack([boxes[:, :2], front], axis=1), colors=colour, linewidths=1.6,
                                     zorder=3), autolim=False)
    if texts is not None:
        # at the box's own top-most corner, just above it: the bounding corner (max x, max y) of a rotated box lies
        # outside it, and in a crowded frame that is nearer a neighbour than its own box
        for (x, y), t in zip(label_anchors(boxes), texts):
            # dark text on an opaque white tag edged in the box's colour: readable on the dark background and on
            # the points (the box's own colour as text was low-contrast at 8 pt)
            ax.text(x, y, t, color="#111111", fontsize=10, fontweight="bold", zorder=4, clip_on=True, ha="center",
                    va="bottom", bbox={"facecolor": "white", "alpha": 0.9, "pad": 1.5, "edgecolor": colour,
                                       "linewidth": 1.2})


def render_bev(
    points: np.ndarray,
    boxes: np.ndarray,
    out: str | Path,
    names: Sequence[str] | None = None,
    det_boxes: np.ndarray | None = None,
    det_scores: np.ndarray | None = None,
    extent: tuple[float, float, float, float] | None = None,
    size: tuple[int, int] = (1000, 1000),
    title: str = "",
    det_label: str = "detections",
) -> None:
    """Bird's-eye view PNG (``size = (W, H)`` pixels) of a scan with its boxes, looking down the sensor's +z.

    ``points`` (N, >=3) sensor frame, metres, coloured by z; ``boxes`` (M,7) ground truth in green, labelled with
    ``names``; ``det_boxes`` (K,7) detections in red (dashed), labelled with ``det_scores``, named ``det_label`` in
    the legend. Each box shows its
    heading as a line from the centre to its front edge. ``extent`` ``(xmin, xmax, ymin, ymax)`` metres, default:
    the points' 0.5-99.5 percentiles plus every box. The axes are equal: x to the right, y up (a top view of the
    right-handed frame, so a positive yaw turns counter-clockwise on the picture).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, np.asarray(points).shape[-1] if len(points) else 3)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    dets = np.zeros((0, 7)) if det_boxes is None else np.asarray(det_boxes, dtype=np.float64).reshape(-1, 7)
    xmin, xmax, ymin, ymax = extent if extent is not None else _auto_extent(points, [boxes, dets])
    fig = _figure(size)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor("#111318")
    z = points[:, 2] if len(points) else np.zeros(1)
    zlo, zhi = (float(np.percentile(z, 1)), float(np.percentile(z, 99))) if len(points) else (0.0, 1.0)
    norm = _norm(zlo, max(zhi, zlo + 1e-3))
    fig.colorbar(_mappable(norm, "viridis"), ax=ax, fraction=0.035, pad=0.01, label="z (m, sensor frame)")
    ax.plot([0], [0], marker=(3, 0, -90), markersize=12, color="white", zorder=5)  # the sensor, pointing along +x
    _draw_bev_boxes(ax, boxes, GT_COLOUR, None if names is None else list(names))
    if len(dets):
        texts = None if det_scores is None else [f"{s:.2f}" for s in np.asarray(det_scores).reshape(-1)]
        _draw_bev_boxes(ax, dets, DET_COLOUR, texts, dashed=True)
    # datalim: keep 1 m = 1 m on both axes but grow the window (around the extent) to fill the picture instead of
    # leaving empty margins; fixed limits would conflict with that, so the extent goes in as data limits.
    ax.dataLim.set_points(np.array([[xmin, ymin], [xmax, ymax]]))
    ax.ignore_existing_data_limits = False
    ax.margins(0)
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    legend = [f"ground truth ({len(boxes)})"]
    handles = [_line(GT_COLOUR, "-")]
    if det_boxes is not None:
        legend.append(f"{det_label} ({len(dets)})")
        handles.append(_line(DET_COLOUR, "--"))
    ax.legend(handles, legend, loc="upper right", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    ax.apply_aspect()
    if len(points):
        # Points are rasterised here, one screen pixel per cell, highest z on top, then shown as one image: far
        # faster than a scatter of 10^5 markers, and it looks the same at this size.
        xl, yl = ax.get_xlim(), ax.get_ylim()
        win = ax.get_window_extent()
        ax.set_autoscale_on(False)
        ax.imshow(_raster_points(points, xl, yl, (int(win.width), int(win.height)), norm), origin="lower",
                  extent=(xl[0], xl[1], yl[0], yl[1]), interpolation="nearest", zorder=1)
    _save_figure(fig, out)


def _norm(lo: float, hi: float):
    from matplotlib.colors import Normalize

    return Normalize(lo, hi, clip=True)


def _mappable(norm, cmap: str):
    from matplotlib.cm import ScalarMappable

    return ScalarMappable(norm=norm, cmap=cmap)


def _raster_points(points: np.ndarray, xlim: tuple[float, float], ylim: tuple[float, float], shape: tuple[int, int],
                   norm) -> np.ndarray:
    """(H, W, 4) RGBA float image of points seen from above over ``xlim x ylim``: each pixel shows the highest
    point in it (viridis by z through ``norm``), grown to 2 x 2 pixels so single returns stay visible; empty pixels
    are transparent."""
    from matplotlib import colormaps

    W, H = max(shape[0], 1), max(shape[1], 1)
    ix = np.floor((points[:, 0] - xlim[0]) / (xlim[1] - xlim[0]) * W).astype(np.int64)
    iy = np.floor((points[:, 1] - ylim[0]) / (ylim[1] - ylim[0]) * H).astype(np.int64)
    ok = (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H)
    top = np.full((H, W), -np.inf)
    np.maximum.at(top, (iy[ok], ix[ok]), points[ok, 2])
    grown = top.copy()
    grown[1:, :] = np.maximum(grown[1:, :], top[:-1, :])
    grown[:, 1:] = np.maximum(grown[:, 1:], grown[:, :-1])
    filled = np.isfinite(grown)
    rgba = colormaps["viridis"](norm(np.where(filled, grown, 0.0)))
    rgba[~filled, 3] = 0.0
    return rgba


def _line(colour: str, ls: str):
    from matplotlib.lines import Line2D

    return Line2D([0], [0], color=colour, ls=ls, lw=2)


def _box_lines(boxes: np.ndarray) -> np.ndarray:
    """(N*12, 2, 3) edge segments of (N,7) boxes."""
    c = box_corners(boxes)
    return np.concatenate([c[:, BOX_EDGES[:, 0]], c[:, BOX_EDGES[:, 1]]], axis=-1).reshape(-1, 2, 3)


def _ensure_offscreen_gl() -> None:
    # Without a display, VTK's default X window fails (and logs a warning) before any fallback; ask for EGL directly.
    # setdefault: a user's own choice (e.g. vtkOSOpenGLRenderWindow) wins.
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def render_frame_3d(
    points: np.ndarray,
    boxes: np.ndarray,
    out: str | Path,
    det_boxes: np.ndarray | None = None,
    size: tuple[int, int] = (1200, 900),
    title: str | None = None,
) -> None:
    """3D PNG (``size = (W, H)`` pixels) of a scan (sensor frame, metres; points coloured by z) with ground-truth
    boxes (green wireframes) and detections (red), seen from behind and above the sensor, rendered off-screen by VTK,
    with an x / y / z axes marker (sensor frame) in the lower left and ``title`` in the upper left.

    Raises :class:`RenderError` when VTK cannot render off-screen here, or renders a blank image.
    """
    _ensure_offscreen_gl()
    try:
        import pyvista as pv
    except ImportError as e:  # pragma: no cover - pyvista is a hard dependency
        raise RenderError(f"3D view needs pyvista: {e}") from None
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    try:
        plotter = pv.Plotter(off_screen=True, window_size=list(size))
    except Exception as e:  # VTK raises assorted errors when no OpenGL context exists
        raise RenderError(f"3D view: VTK cannot open an off-screen window: {e}") from None
    try:
        plotter.set_background("#111318")
        if len(pts):
            cloud = pv.PolyData(pts)
            cloud["z"] = pts[:, 2]
            plotter.add_mesh(cloud, scalars="z", cmap="viridis", point_size=2.0, render_points_as_spheres=False,
                             show_scalar_bar=True, scalar_bar_args={
                                 "title": "z (m, sensor frame)", "vertical": True, "position_x": 0.9,
                                 "position_y": 0.25, "height": 0.5, "width": 0.05, "color": "white",
                                 "title_font_size": 14, "label_font_size": 12, "fmt": "%.1f"})
        for b, colour in ((boxes, GT_COLOUR), (det_boxes, DET_COLOUR)):
            if b is None or len(b) == 0:
                continue
            seg = _box_lines(np.asarray(b, dtype=np.float64).reshape(-1, 7)).reshape(-1, 3)
            plotter.add_mesh(pv.line_segments_from_points(seg), color=colour, line_width=3)
        extent = float(np.linalg.norm(np.ptp(np.percentile(pts, [5, 95], axis=0), axis=0))) if len(pts) else 1.0
        # the sensor: at the origin, facing +x (said in the key below, so the arrow explains itself)
        plotter.add_mesh(pv.Arrow(start=(0, 0, 0), direction=(1, 0, 0), scale=max(1.0, 0.05 * extent)), color="white",
                         ambient=0.6)
        plotter.add_axes(xlabel="x", ylabel="y", zlabel="z", line_width=3)  # the sensor frame's axes
        # a scale: the scene's bounds with tick labels in metres on the axes' titles
        plotter.show_bounds(xtitle="x forward (m)", ytitle="y left (m)", ztitle="z up (m)", color="white",
                            font_size=10, location="outer", ticks="outside", fmt="%.0f")
        if title:
            plotter.add_text(title, position="upper_left", font_size=10, color="white")
        key = ["white arrow: the sensor (origin, facing +x)", "green boxes: ground truth"]
        if det_boxes is not None and len(det_boxes):
            key.append("red boxes: detections")
        plotter.add_text("\n".join(key), position="lower_right", font_size=9, color="white")
        # Camera: behind and above the scene, looking along +x and down; then fit the scene's robust bounds (the
        # 1-99 percentiles of the points, plus every box) so a few far returns do not shrink everything.
        parts = [np.zeros((1, 3))]
        if len(pts):
            parts += [np.percentile(pts, 1, axis=0)[None], np.percentile(pts, 99, axis=0)[None]]
        for b in (boxes, det_boxes):
            if b is not None and len(b):
                parts.append(box_corners(np.asarray(b, dtype=np.float64).reshape(-1, 7)).reshape(-1, 3))
        allp = np.concatenate(parts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        focus = 0.5 * (lo + hi)
        plotter.camera_position = [tuple(focus + np.array([-1.0, 0.0, 0.8])), tuple(focus), (0.0, 0.0, 1.0)]
        plotter.reset_camera(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        plotter.camera.zoom(1.25)
        image = plotter.screenshot(return_img=True)
    except RenderError:
        raise
    except Exception as e:
        raise RenderError(f"3D view: off-screen rendering failed: {e}") from None
    finally:
        plotter.close()
    if image is None or image.reshape(-1, image.shape[-1]).std(axis=0).max() == 0:
        raise RenderError("3D view: VTK rendered a blank image (no working off-screen OpenGL: EGL or OSMesa)")
    _save_rgb(image, out)


# ----------------------------------------------------------------------------------------------------------- houses


def render_house(
    vertices: np.ndarray,
    faces: np.ndarray,
    out: str | Path,
    highlight_faces: np.ndarray | None = None,
    highlight_boxes: np.ndarray | None = None,
    viewpoints: np.ndarray | None = None,
    hidden_faces: np.ndarray | None = None,
    z_ranges: Sequence[tuple[float, float]] | None = None,
    panel_titles: Sequence[str] | None = None,
    size: tuple[int, int] = (1200, 1200),
    title: str = "",
    highlight_label: str = "highlighted objects",
) -> None:
    """Top-down PNG of a house mesh (Matterport world frame, z up, metres), ``size = (W, H)`` pixels.

    Faces that face up (normal z > 0.1: floors, seats, table tops) are painted in grey by height, lowest first, so
    upper surfaces cover lower ones; faces that face down (ceilings, seen from above their back) are left out, so
    rooms stay visible; steep faces (walls) are drawn as dark outlines. ``z_ranges`` makes one panel per
    ``(zmin, zmax)``, side by side, each with only the faces, boxes and viewpoints whose z lies in ``[zmin, zmax)``
    (the levels of a multi-level house); default: one panel with everything.

    ``highlight_faces`` (F,) bool marks faces to paint in orange (objects of the chosen class); ``highlight_boxes``
    (K,7) world-frame boxes are outlined in orange; ``viewpoints`` (V,4) ``[x, y, z, yaw]`` (world frame, metres /
    radians CCW about +z) are drawn as blue arrows (position and heading). ``hidden_faces`` (F,) bool are left out
    (e.g. ceilings whose top side faces up, as roofs of synthetic houses do).
    """
    from matplotlib.collections import PolyCollection

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    hl = np.zeros(len(f), dtype=bool) if highlight_faces is None else np.asarray(highlight_faces, dtype=bool)
    boxes = np.zeros((0, 7)) if highlight_boxes is None else np.asarray(highlight_boxes, dtype=np.float64)
    boxes = boxes.reshape(-1, 7)
    vp = np.zeros((0, 4)) if viewpoints is None else np.asarray(viewpoints, dtype=np.float64).reshape(-1, 4)
    tri = v[f]  # (F,3,3)
    cz = tri[:, :, 2].mean(axis=1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    nz = np.divide(n[:, 2], norm, out=np.zeros(len(f)), where=norm > 0)
    ranges = list(z_ranges) if z_ranges else [(-np.inf, np.inf)]
    lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
    margin = 0.03 * max(float((hi - lo).max()), 1.0)

    fig = _figure(size)
    axes = np.atleast_1d(fig.subplots(1, len(ranges), squeeze=False).reshape(-1))
    for k, (ax, (z0, z1)) in enumerate(zip(axes, ranges)):
        keep = (cz >= z0) & (cz < z1)
        if hidden_faces is not None:
            keep &= ~np.asarray(hidden_faces, dtype=bool)
        up = keep & (nz > 0.1)
        steep = keep & (np.abs(nz) <= 0.1) & (norm > 0)
        if up.any():
            idx = np.flatnonzero(up)
            idx = idx[np.argsort(cz[idx], kind="stable")]  # painter's order: low surfaces first
            z = cz[idx]
            span = max(float(z.max() - z.min()), 1e-6)
            grey = 0.55 + 0.4 * (z - z.min()) / span
            colours = np.stack([grey, grey, grey, np.ones_like(grey)], axis=1)
            colours[hl[idx]] = (1.0, 0.5, 0.05, 1.0)
            ax.add_collection(PolyCollection(tri[idx, :, :2], facecolors=colours, edgecolors="face", linewidths=0.2,
                                             antialiased=False, zorder=1), autolim=False)
        if steep.any():
            idx = np.flatnonzero(steep)
            ax.add_collection(PolyCollection(tri[idx, :, :2], facecolors="none", edgecolors="#303030",
                                             linewidths=0.4, zorder=2), autolim=False)
        sel = (boxes[:, 2] >= z0) & (boxes[:, 2] < z1)
        _draw_bev_boxes(ax, boxes[sel], HIGHLIGHT_COLOUR, None)
        p = vp[(vp[:, 2] >= z0) & (vp[:, 2] < z1)]
        if len(p):
            ax.quiver(p[:, 0], p[:, 1], np.cos(p[:, 3]), np.sin(p[:, 3]), color=VIEWPOINT_COLOUR, angles="xy",
                      scale_units="xy", scale=1.0 / 0.6, width=0.004, zorder=5)
            ax.scatter(p[:, 0], p[:, 1], s=14, color=VIEWPOINT_COLOUR, zorder=5)
        ax.set_xlim(lo[0] - margin, hi[0] + margin)
        ax.set_ylim(lo[1] - margin, hi[1] + margin)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (m, world)")
        ax.set_ylabel("y (m, world)")
        if panel_titles is not None:
            ax.set_title(panel_titles[k])
    fig.suptitle(title)
    # what the colours mean, once for every panel, under the title
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=(0.6, 0.6, 0.6), edgecolor="none", label="floors and tops (lighter = higher)"),
               Line2D([], [], color="#303030", lw=1.2, label="walls (outlines)")]
    if hl.any() or len(boxes):
        handles.append(Patch(facecolor=HIGHLIGHT_COLOUR, edgecolor=HIGHLIGHT_COLOUR, label=highlight_label))
    if len(vp):
        handles.append(Line2D([], [], color=VIEWPOINT_COLOUR, marker="o", markersize=4, lw=1.6,
                              label="viewpoints (position, heading)"))
    fig.tight_layout(rect=(0.0, 0.03, 1.0, 0.9))
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.945), ncol=len(handles), fontsize=9,
               frameon=False)
    _save_figure(fig, out)


# ------------------------------------------------------------------------------------------------ dataset readers


def frame_boxes(root: str | Path, frame_id: str, split_dir: str = "training") -> tuple[np.ndarray, list[str]]:
    """Ground truth of a frame: (N,7) sensor-frame boxes of the non-DontCare rows of ``label_2`` and their names
    (``split_dir`` as in :func:`mpchair.analysis.stats.load_points`)."""
    paths = frame_paths(root, frame_id, split_dir)
    labels = read_labels(paths.label_2).objects()
    return labels_to_boxes(labels, read_calib(paths.calib)), [str(n) for n in labels.names]


def result_boxes(results: str | Path, frame_id: str, calib: Calib) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Detections of a frame from a KITTI result file ``<results>/<id>.txt`` (16 columns, with score): (K,7)
    sensor-frame boxes (through the frame's ``calib``), scores (K,) and names. A 15-column file is an
    :class:`InputError` (it has no scores)."""
    path = Path(results) / f"{frame_id}.txt"
    if not Path(results).is_dir():
        raise InputError("result folder not found (--results takes a folder of KITTI result files, e.g. detector "
                         "eval's OUT/data)", results)
    if not path.is_file():
        # result folders hold only the frames of the split they were evaluated on (detector eval --split)
        raise InputError(f"result file not found: frame {frame_id} is not among these results, which hold the frames "
                         "of the split they were evaluated on (e.g. ImageSets/val.txt)", path)
    labels = read_labels(path).objects()
    if labels.score is None and len(labels):
        raise InputError("result file has 15 columns; detections need the 16th (score)", path)
    scores = np.zeros(0) if labels.score is None else labels.score
    return labels_to_boxes(labels, calib), scores, [str(n) for n in labels.names]


def house_viewpoints(dataset: str | Path, house_id: str) -> np.ndarray:
    """(V,4) ``[x, y, z, yaw]`` (Matterport world frame, metres / radians CCW about +z) of every frame of ``dataset``
    taken in house ``house_id``: frames from ``manifest.json`` (its ``house`` ids), poses from
    ``training/pose/<id>.txt`` (3x4 row-major sensor → world; yaw = heading of the sensor's +x). A dataset
    without a manifest is an :class:`InputError` (the house of a frame is known only there)."""
    from mpchair.dataset.manifest import read_manifest

    dataset = Path(dataset)
    manifest = read_manifest(dataset)
    if manifest is None:
        raise InputError("no manifest.json (needed for the house of each frame)", dataset)
    ids = [f.frame for f in manifest.frames if f.house == house_id]
    out = np.zeros((len(ids), 4))
    for k, fid in enumerate(ids):
        pose_path = dataset / "training" / "pose" / f"{fid}.txt"
        try:
            values = [float(t) for t in pose_path.read_text(encoding="utf-8").split()]
        except FileNotFoundError:
            raise InputError("pose file not found", pose_path) from None
        except ValueError as e:
            raise InputError(f"not a number: {e}", pose_path, 1) from None
        if len(values) != 12:
            raise InputError(f"expected 12 numbers (3x4 sensor -> world), got {len(values)}", pose_path, 1)
        T = np.eye(4)
        T[:3] = np.asarray(values).reshape(3, 4)
        try:
            yaw = yaw_of(T, atol=1e-4)
        except ValueError as e:
            raise InputError(str(e), pose_path, 1) from None
        out[k] = (T[0, 3], T[1, 3], T[2, 3], yaw)
    return out


# ------------------------------------------------------------------------------------------------ whole pictures

#: ``mpchair view``'s default ceiling cut on an mpchair dataset: drop points this high above the floor (metres) or
#: higher. Chairs (backs up to ~1.2 m), tables and sofas stay; ceilings (synthetic houses 2.6-2.8 m, Matterport3D
#: homes ~2.4 m and up) and the top of the walls go, so the bird's-eye view shows the room instead of its ceiling.
CEILING_CUT = 2.0


def default_zmax(dataset: str | Path) -> float | None:
    """``mpchair view``'s default ``zmax`` for ``dataset`` (sensor frame, metres): on an mpchair dataset
    :data:`CEILING_CUT` above the floor, i.e. ``CEILING_CUT - height`` with the sensor height above the floor of the
    manifest's ``config.viewpoints.height`` (1.0 m, so z = 1.0, at generate's default ``--height 1.0``). ``None``
    (keep every point) for a folder without a manifest (real KITTI: outdoors, no ceiling to cut). A ``config``
    without a positive sensor height, or a file that is not an mpchair manifest, is an :class:`InputError`."""
    from mpchair.dataset.manifest import read_manifest

    manifest = read_manifest(dataset)
    if manifest is None:
        return None
    viewpoints = manifest.config.get("viewpoints")
    height = viewpoints.get("height") if isinstance(viewpoints, dict) else None
    if isinstance(height, bool) or not isinstance(height, (int, float)) or not 0 < height < float("inf"):
        raise InputError(f"config.viewpoints.height: expected the sensor height above the floor in metres, got "
                         f"{height!r}", Path(dataset) / "manifest.json")
    return CEILING_CUT - float(height)



def stream_zmax(stream: str | Path) -> float:
    """``mpchair view``'s default ``zmax`` for a stream folder: :data:`CEILING_CUT` above the floor, with the sensor
    height of the ``--height`` in ``stream.json``'s command (1.0 m when it names none)."""
    from mpchair.recording.sources import read_stream_meta

    stream_meta = read_stream_meta(Path(stream))
    meta, path = stream_meta.data, stream_meta.path
    command = meta.get("command") if isinstance(meta.get("command"), list) else []
    height = 1.0
    if "--height" in command[:-1]:
        try:
            height = float(command[command.index("--height") + 1])
        except ValueError:
            raise InputError("malformed stream file (--height in its command is no number)", path) from None
    return CEILING_CUT - height


def frame_picture(
    dataset: str | Path,
    frame_id: str,
    out: str | Path,
    results: str | Path | None = None,
    out_3d: str | Path | None = None,
    fov_crop: bool = False,
    size: tuple[int, int] = (1000, 1000),
    extent: tuple[float, float, float, float] | None = None,
    zmax: float | None = None,
    split_dir: str = "training",
) -> dict:
    """The pictures of one frame of a KITTI-layout dataset (``split_dir`` ``""``: of a stream's sequence folder):
    the bird's-eye view at ``out`` (:func:`render_bev`) and,
    when ``out_3d`` is given, the 3D view there (:func:`render_frame_3d`, rendered first so that a machine without
    off-screen OpenGL fails before anything is written). ``results`` is a folder of KITTI result files (16 columns)
    whose detections are drawn in red. ``zmax`` (sensor frame, metres) drops points at or above it from both views,
    e.g. the ceiling of an indoor scan that would otherwise cover the floor in the bird's-eye view (``mpchair view``
    passes :func:`default_zmax` unless told otherwise); ``None`` keeps every point. Returns ``{frame, points (drawn),
    zmax, above_zmax (points left out), boxes, detections, out, out_3d}``.
    """
    from mpchair.analysis.stats import load_points

    paths = frame_paths(dataset, frame_id, split_dir)
    points = load_points(dataset, frame_id, fov_crop, split_dir)
    n_loaded = len(points)
    if zmax is not None:
        points = points[points[:, 2] < zmax]
    boxes, names = frame_boxes(dataset, frame_id, split_dir)
    dets = scores = None
    if results is not None:
        dets, scores, _ = result_boxes(results, frame_id, read_calib(paths.calib))
    where = f"{Path(dataset).parent.parent.name} sequence {Path(dataset).name}" if not split_dir else Path(dataset).name
    title = (f"{where} frame {frame_id}: {len(points)} points" + (" (FOV-cropped)" if fov_crop else "")
             + ("" if zmax is None else f", z < {zmax:g} m"))
    if out_3d is not None:
        render_frame_3d(points, boxes, out_3d, det_boxes=dets, size=size, title=title)
    render_bev(points, boxes, out, names=names, det_boxes=dets, det_scores=scores, extent=extent, size=size,
               title=title)
    return {"frame": frame_id, "points": int(len(points)), "zmax": zmax, "above_zmax": n_loaded - len(points),
            "boxes": int(len(boxes)),
            "detections": None if dets is None else int(len(dets)), "out": str(out),
            "out_3d": None if out_3d is None else str(out_3d)}


def house_picture(
    root: str | Path,
    house_id: str,
    out: str | Path,
    category: str = "chair",
    dataset: str | Path | None = None,
    level: int | None = None,
    size: tuple[int, int] | None = None,
) -> dict:
    """Top-down picture of house ``house_id`` found under ``root`` (:func:`mpchair.matterport.find_houses`): faces of
    objects of mpcat40 class ``category`` in orange with their aligned boxes, and, with ``dataset``, the viewpoints
    (position + heading) of its frames taken in this house (:func:`house_viewpoints`). ``level`` keeps only faces
    inside that level's z range (``House.levels[level].bbox``). ``size`` (W, H) pixels; default: 800 x 860 per panel
    side by side (one panel per level). Returns ``{house, faces, objects, viewpoints, out}``.
    """
    from mpchair.matterport import aligned_boxes, find_houses, read_house, resolve_categories, resolve_category

    houses = find_houses(root)
    if house_id not in houses:
        raise InputError(f"house {house_id!r} not found (found: {', '.join(houses) or 'none'})", root)
    wanted = resolve_categories(category)
    viewpoints = house_viewpoints(dataset, house_id) if dataset is not None else None
    house = read_house(houses[house_id])
    positions = np.asarray([i for i, o in enumerate(house.objects) if o.mpcat40_index in wanted], dtype=np.int64)
    objs = [house.objects[i] for i in positions]
    if level is not None and not 0 <= level < len(house.levels):
        raise InputError(f"house {house_id} has {len(house.levels)} level(s); --level {level} is out of range")
    # One panel per level, so an upper floor never hides the one below. Levels split the z axis where each one's bbox
    # starts (less a slab margin: floor faces may sit a little below a level's bbox); the lowest reaches down to -inf
    # and the highest up to +inf, so every face belongs to exactly one level.
    ordered = sorted(house.levels, key=lambda lv: float(lv.bbox[2]))
    starts = [-np.inf] + [float(lv.bbox[2]) - LEVEL_MARGIN for lv in ordered[1:]] + [np.inf]
    bounds = {lv.index: (starts[k], starts[k + 1]) for k, lv in enumerate(ordered)}
    levels = ordered if level is None else [house.levels[level]]
    z_ranges = [bounds[lv.index] for lv in levels] if levels else None
    titles = [f"level {lv.index}" + (f" ({lv.label})" if lv.label.strip() else "") for lv in levels] or None
    if size is None:  # side-by-side level panels: widen the picture instead of leaving bands above and below
        size = (min(3200, 800 * max(1, len(levels))), 860)
    render_house(house.vertices, house.faces, out, highlight_faces=np.isin(house.face_object, positions),
                 highlight_boxes=aligned_boxes(objs), viewpoints=viewpoints, z_ranges=z_ranges,
                 hidden_faces=house.face_category == resolve_category("ceiling"),
                 panel_titles=titles, size=size, highlight_label=f"{category} objects (and their boxes)",
                 title=f"house {house_id}: {len(objs)} {category} object(s)"
                       + ("" if viewpoints is None else f", {len(viewpoints)} viewpoints"))
    return {"house": house_id, "faces": int(len(house.faces)), "objects": len(objs),
            "viewpoints": None if viewpoints is None else int(len(viewpoints)), "out": str(out)}
