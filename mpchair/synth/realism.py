"""How much a synthetic house looks like a Matterport3D reconstruction: the :class:`Realism` knobs and the mesh
operations behind them (house frame, metres, z up).

Real MP3D house meshes are reconstructions, not CAD: surfaces are noisy and slightly wavy, patches are missing where
the depth camera got nothing back (windows, mirrors, glossy or dark surfaces, thin chair legs and backs, the
undersides of furniture, the floor under tables), objects' segments are fragmentary (some faces unlabelled) or bleed
onto the floor around them, and floating fragments float about. Every knob here imitates one of these, draws from its
own seeded stream (:func:`realism_rng`), and leaves every object's ``.house`` box its true box: boxes are measured on
the clean geometry before any artifact is applied, and noisy object vertices are kept inside that box
(:data:`BOX_SLACK`). ``CLEAN`` turns everything off, so ``synthesize_house(seed, realism=CLEAN)`` is bit for bit the
house the synthesizer made before realism existed.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mpchair.synth.primitives import Mesh, box

#: How far (m) a noisy vertex of an object may stand outside the object's true box: under half the label filters' box
#: margin (``LabelFilters.box_margin`` = 0.01), so noise alone never puts an object's hits outside its box.
BOX_SLACK = 0.004


@dataclasses.dataclass(frozen=True)
class Realism:
    """Named, seeded knobs of MP3D-like reconstruction artifacts and clutter (lengths in metres; rates are
    probabilities per item unless said otherwise). All zero (:data:`CLEAN`): today's clean procedural houses.

    * ``room_size``: when > 0, every house's rooms are scaled to this mean width (m; the procedural rooms are
      3.4-5.2 m, mean ~4.2). Real MP3D homes are bigger: longer sightlines, sparser far points, a higher pseudo-image
      density; one mean size for every house keeps that density steady from house to house.
    * ``room_size_spread``: each house's mean width is ``room_size`` times a factor drawn in 1 ± this (homes differ
      in size: the density's tail, its maximum, comes from the bigger ones).
    * ``open_plan``: per door between two rooms, a wide opening (1.6 m up to the wall less 1.2 m) instead.
    * ``cell``: walls, floors and ceilings are re-meshed as grids of this cell size when any surface knob is on (real
      meshes are dense; noise, waves and holes need vertices to act on).
    * ``vertex_noise``: every vertex moves by at most this much (uniform direction, uniform length), the same for
      coincident vertices so no cracks open; the scanner's depth noise (~1-2 cm).
    * ``wave_amplitude`` / ``wave_length``: a smooth displacement of walls, floors and ceilings (at most the
      amplitude), the slow warps of a registered reconstruction.
    * ``surface_holes``: missing patches (radius ``hole_radius``) per 10 m² of wall, floor and ceiling: glossy and
      dark surfaces the depth camera did not see.
    * ``mirror_holes``: per bathroom or bedroom, a mirror-sized hole through a wall (mirrors reconstruct as holes).
    * ``floor_under_tables``: per table, the floor under it is missing (the camera never sees it).
    * ``thin_part_holes``: per thin chair part (legs, posts, thinner than 5 cm), a few of its triangles missing.
    * ``open_undersides``: per furniture part, its underside is missing (open, non-watertight furniture).
    * ``chair_holes``: per chair, a see-through hole in its seat or back, with the chair's label on the floor seen
      through and around it (``bleed_width`` deep): MP3D's label image disagrees with its geometry there, so hits
      labelled chair land outside its box (the "holes" filter, ``in_box_fraction``, and with a hidden chair
      ``points_in_box``).
    * ``chair_ghosts`` / ``ghost_distance``: per chair, a small floating fragment this far (m) beside its box carrying
      the chair's label (a split object: a piece mis-registered from another scan).
    * ``unlabelled_parts``: per piece of furniture with several parts, one part in segment -1 (fragmentary objects).
    * ``fragments``: extra small floating unlabelled fragments per room.
    * ``clutter``: how many clutter items a room gets (plants, shelving, counters, cushions, objects on tables and
      floors, stool-like chairs; 1 = the default amount, 0 = none).
    * ``doors``: per door opening, an open door leaf in it.
    * ``chair_mix``: the chairs are drawn from the mix calibrated to the original dataset's mean chair box
      (:data:`mpchair.synth.house.MP3D_CHAIRS`: rocking chairs, a chaise longue quota per house, indoor sizes)
      instead of the procedural recipe's.
    """

    name: str = "custom"
    room_size: float = 0.0
    room_size_spread: float = 0.0
    open_plan: float = 0.0
    cell: float = 0.25
    vertex_noise: float = 0.0
    wave_amplitude: float = 0.0
    wave_length: float = 3.0
    surface_holes: float = 0.0
    hole_radius: tuple[float, float] = (0.08, 0.25)
    mirror_holes: float = 0.0
    floor_under_tables: float = 0.0
    thin_part_holes: float = 0.0
    open_undersides: float = 0.0
    chair_holes: float = 0.0
    bleed_width: tuple[float, float] = (0.1, 0.45)
    chair_ghosts: float = 0.0
    ghost_distance: tuple[float, float] = (0.8, 3.0)
    unlabelled_parts: float = 0.0
    fragments: float = 0.0
    clutter: float = 0.0
    doors: float = 0.0
    chair_mix: bool = False

    def __post_init__(self) -> None:
        rates = ("surface_holes", "mirror_holes", "floor_under_tables", "thin_part_holes", "open_undersides",
                 "chair_holes", "chair_ghosts", "unlabelled_parts", "fragments", "clutter", "doors")  # fmt: skip
        for k in rates + ("vertex_noise", "wave_amplitude"):
            if getattr(self, k) < 0:
                raise ValueError(f"realism {k} must be >= 0")
        for k in ("mirror_holes", "floor_under_tables", "thin_part_holes", "open_undersides", "chair_holes",
                  "chair_ghosts", "unlabelled_parts", "doors"):  # fmt: skip
            if getattr(self, k) > 1:
                raise ValueError(f"realism {k} is a probability, got {getattr(self, k)}")
        if self.cell <= 0 or self.wave_length <= 0 or self.room_size < 0:
            raise ValueError("realism cell and wave_length must be > 0, room_size >= 0")
        if not 0 <= self.room_size_spread < 1:
            raise ValueError(f"realism room_size_spread must be in [0, 1), got {self.room_size_spread}")
        if not 0 <= self.open_plan <= 1:
            raise ValueError(f"realism open_plan is a probability, got {self.open_plan}")

    @property
    def remesh(self) -> bool:
        """Whether walls, floors and ceilings are re-meshed as grids (some surface knob needs vertices)."""
        return bool(self.vertex_noise or self.wave_amplitude or self.surface_holes or self.mirror_holes
                    or self.floor_under_tables)  # fmt: skip

    @property
    def is_clean(self) -> bool:
        """Every knob off: the house is the clean procedural one."""
        return self == dataclasses.replace(CLEAN, name=self.name)


#: No artifacts, no clutter: the procedural houses as they were before the realism model (same bytes per seed).
CLEAN = Realism(name="clean")

#: Calibrated so that ``mpchair generate --height 1.25 --robot-radius 0.1`` with ``mp3d-depth90`` meets the original
#: dataset's density and filter statistics (docs/matterport.md, "Realism").
DEFAULT = Realism(
    name="default", room_size=4.9, room_size_spread=0.1, open_plan=0.5, vertex_noise=0.012, wave_amplitude=0.01,
    surface_holes=0.6, mirror_holes=0.5, floor_under_tables=0.7, thin_part_holes=0.3, open_undersides=0.5,
    chair_holes=0.2, chair_ghosts=0.7, unlabelled_parts=0.15, fragments=1.5, clutter=1.0, doors=0.7, chair_mix=True,
)  # fmt: skip

REALISM_PRESETS: dict[str, Realism] = {"clean": CLEAN, "default": DEFAULT}


def realism_preset(name: str) -> Realism:
    """The preset called ``name`` (``clean`` or ``default``)."""
    try:
        return REALISM_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown realism preset {name!r}; known: {', '.join(REALISM_PRESETS)}") from None


def realism_rng(seed: int) -> np.random.Generator:
    """The realism stream of house ``seed``: separate from the layout stream, so a clean house draws nothing from it
    and keeps its bytes."""
    return np.random.default_rng([int(seed), 27])


# ------------------------------------------------------------------------------------------------ mesh operations


def grid_box(lo, hi, cell: float) -> Mesh:
    """Axis-aligned closed box from ``lo`` to ``hi`` whose six sides are grids of about ``cell`` squares (outward
    counter-clockwise triangles; neighbouring sides share their edge vertices' positions, not indices)."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    verts, faces = [], []
    n_v = 0
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3  # (a, b, axis) is right-handed
        na = max(1, int(math.ceil((hi[a] - lo[a]) / cell - 1e-9)))
        nb = max(1, int(math.ceil((hi[b] - lo[b]) / cell - 1e-9)))
        ua, ub = np.linspace(lo[a], hi[a], na + 1), np.linspace(lo[b], hi[b], nb + 1)
        ga, gb = np.meshgrid(ua, ub, indexing="ij")
        k = np.arange((na + 1) * (nb + 1)).reshape(na + 1, nb + 1)
        q0, q1, q2, q3 = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
        for side, value in ((+1, hi[axis]), (-1, lo[axis])):
            p = np.empty((ga.size, 3))
            p[:, a], p[:, b], p[:, axis] = ga.ravel(), gb.ravel(), value
            tri = np.concatenate([np.stack([q0, q1, q2], 1), np.stack([q0, q2, q3], 1)])
            if side < 0:
                tri = tri[:, ::-1]
            verts.append(p)
            faces.append(tri + n_v)
            n_v += len(p)
    return np.vstack(verts), np.vstack(faces).astype(np.int64)


def box_extent(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lo, hi)`` when the mesh is exactly an axis-aligned :func:`~mpchair.synth.primitives.box`, else ``None``."""
    if len(verts) != 8 or len(faces) != 12:
        return None
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    ref_v, ref_f = box(lo, hi)
    if np.array_equal(ref_f, faces) and np.allclose(ref_v, verts, atol=1e-12):
        return lo, hi
    return None


def face_centres(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,3) centroids of the triangles."""
    return verts[faces].mean(axis=1)


def face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,3) unit normals of the triangles (right-hand rule)."""
    t = verts[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def in_discs(points: np.ndarray, discs: np.ndarray) -> np.ndarray:
    """(N,) bool: ``points`` (N,3) within any sphere of ``discs`` (K,4) [x, y, z, radius]."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(points), dtype=bool)
    if len(discs) == 0 or len(points) == 0:
        return out
    tree = cKDTree(points)
    for idx in tree.query_ball_point(discs[:, :3], discs[:, 3]):
        out[np.asarray(idx, dtype=np.int64)] = True
    return out


def vertex_noise(points: np.ndarray, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """(N,3) offsets of length at most ``amplitude`` (uniform direction, uniform length); vertices at the same
    position (to 0.1 mm) get the same offset, so noise opens no cracks between parts that touch."""
    if amplitude <= 0 or len(points) == 0:
        return np.zeros_like(points)
    _, inv = np.unique(np.round(points * 1e4).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = int(inv.max()) + 1
    d = rng.normal(size=(n, 3))
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    r = amplitude * rng.random(n)
    return (d * r[:, None])[inv]


def wave_field(points: np.ndarray, amplitude: float, length: float, phases: np.ndarray) -> np.ndarray:
    """(N,3) smooth offsets of length at most ``amplitude``: per axis a product of sines of wavelength ``length``
    (``phases`` (3,3) radians), a slow warp that keeps touching surfaces touching."""
    if amplitude <= 0 or len(points) == 0:
        return np.zeros_like(points)
    k = 2 * math.pi / length
    out = np.empty_like(points)
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        out[:, axis] = np.sin(k * points[:, a] + phases[axis, 0]) * np.sin(k * points[:, b] + phases[axis, 1])
    return out * (amplitude / math.sqrt(3.0))


def keep_in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, yaw: float, pos: np.ndarray) -> np.ndarray:
    """``points`` (N,3, house frame) clipped into the box ``lo``..``hi`` (object frame at ``pos`` with ``yaw``)
    grown by :data:`BOX_SLACK`: noise must not carry an object outside its true box."""
    c, s = math.cos(yaw), math.sin(yaw)
    p = points - pos
    local = np.column_stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1], p[:, 2]])
    local = np.clip(local, lo - BOX_SLACK, hi + BOX_SLACK)
    world = np.column_stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]])
    return world + pos


def floor_tiles(rects: list[tuple[float, float, float, float]], z: float, tile: float = 0.1) -> Mesh:
    """Flat upward quads (two triangles each, about ``tile`` square) covering local rectangles ``rects``
    (x0, y0, x1, y1) at height ``z``: the label-bleed patch of a chair hole (object frame)."""
    verts, faces = [], []
    for x0, y0, x1, y1 in rects:
        nx = max(1, int(math.ceil((x1 - x0) / tile)))
        ny = max(1, int(math.ceil((y1 - y0) / tile)))
        for i in range(nx):
            for j in range(ny):
                a0, a1 = x0 + (x1 - x0) * i / nx, x0 + (x1 - x0) * (i + 1) / nx
                b0, b1 = y0 + (y1 - y0) * j / ny, y0 + (y1 - y0) * (j + 1) / ny
                k = len(verts) * 4
                verts.append([[a0, b0, z], [a1, b0, z], [a1, b1, z], [a0, b1, z]])
                faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), np.asarray(faces, dtype=np.int64)


def bleed_rects(lo: np.ndarray, hi: np.ndarray, widths) -> list[tuple[float, float, float, float]]:
    """The ring around footprint ``lo``..``hi`` (object frame) with depth ``widths`` (4,) on the -x, +x, -y, +y
    sides: where a chair's label bleeds onto the floor (corner squares belong to the x sides)."""
    wx0, wx1, wy0, wy1 = (float(w) for w in widths)
    x0, y0, x1, y1 = float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])
    out = []
    if wx0 > 0:
        out.append((x0 - wx0, y0 - wy0, x0, y1 + wy1))
    if wx1 > 0:
        out.append((x1, y0 - wy0, x1 + wx1, y1 + wy1))
    if wy0 > 0:
        out.append((x0, y0 - wy0, x1, y0))
    if wy1 > 0:
        out.append((x0, y1, x1, y1 + wy1))
    return out
