"""Procedural furniture for synthetic houses, built from closed triangle parts in an object-local frame.

Object-local frame: origin on the floor under the object, +x = the object's front (where a sitter faces), +y = its
left, z up, metres. Each builder returns ``[(group, vertices, faces), ...]``; ``group`` (0, 1, ...) splits the object
into mesh segments (``E`` records), e.g. legs/base and seat/back. Sizes follow real furniture.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from mpchair.synth.primitives import bar, cbox, cylinder, rotate_z

Part = tuple[int, np.ndarray, np.ndarray]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _legs(d: float, w: float, h: float, size: float, inset: float = 0.0, group: int = 0) -> list[Part]:
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x = sx * (d / 2 - size / 2 - inset)
            y = sy * (w / 2 - size / 2 - inset)
            out.append((group, *cbox(x, y, h / 2, size, size, h)))
    return out


# ---------------------------------------------------------------------------------------------------- chairs


def dining_chair(rng: np.random.Generator) -> list[Part]:
    """Four-leg dining chair: legs, seat, two rear posts and a back panel (about 0.53 x 0.49 x 0.89 m)."""
    w, d = _u(rng, 0.44, 0.54), _u(rng, 0.48, 0.58)
    sh, top, leg = _u(rng, 0.43, 0.48), _u(rng, 0.8, 0.96), 0.035
    parts = _legs(d, w, sh - 0.04, leg)
    parts.append((1, *cbox(0, 0, sh - 0.02, d, w, 0.04)))
    for sy in (-1, 1):
        parts.append((1, *cbox(-(d / 2 - leg / 2), sy * (w / 2 - leg / 2), (sh + top) / 2, leg, leg, top - sh)))
    parts.append((1, *cbox(-(d / 2 - leg / 2), 0, (sh + 0.18 + top - 0.02) / 2, 0.025, w - 2 * leg, top - sh - 0.2)))
    return parts


def armchair(rng: np.random.Generator, width: tuple[float, float] = (0.86, 1.14),
             depth: tuple[float, float] = (0.84, 1.04)) -> list[Part]:
    """Upholstered armchair: short legs, base, seat cushion, back block and two arms (about 1.0 x 0.9 x 0.87 m with
    the default ``width`` and ``depth`` ranges, m)."""
    # Club chairs and wing chairs are wide and deep; these sizes are what makes real MP3D chair boxes long on average.
    w, d = _u(rng, *width), _u(rng, *depth)
    sh, top, arm_h = _u(rng, 0.40, 0.46), _u(rng, 0.78, 0.96), _u(rng, 0.58, 0.68)
    arm_w, back_t = _u(rng, 0.12, 0.2), _u(rng, 0.15, 0.22)
    parts = _legs(d, w, 0.1, 0.05, inset=0.03)
    parts.append((1, *cbox(0, 0, (0.1 + sh - 0.1) / 2, d, w, sh - 0.2)))
    cx0 = -d / 2 + back_t
    parts.append((1, *cbox((cx0 + d / 2) / 2, 0, sh - 0.05, d / 2 - cx0, w - 2 * arm_w, 0.1)))
    parts.append((1, *cbox(-d / 2 + back_t / 2, 0, (0.1 + top) / 2, back_t, w, top - 0.1)))
    for sy in (-1, 1):
        parts.append((1, *cbox((cx0 + d / 2) / 2, sy * (w / 2 - arm_w / 2), (0.1 + arm_h) / 2, d / 2 - cx0, arm_w,
                               arm_h - 0.1)))  # fmt: skip
    return parts


def office_chair(rng: np.random.Generator) -> list[Part]:
    """Office chair: five-star base with casters, gas column, seat, back on a post, optional armrests
    (about 0.66 x 0.64 x 1.0 m)."""
    r, sh, top = _u(rng, 0.31, 0.36), _u(rng, 0.44, 0.5), _u(rng, 0.9, 1.1)
    phase = _u(rng, 0, 2 * math.pi / 5)
    parts: list[Part] = []
    for k in range(5):
        a = phase + k * 2 * math.pi / 5
        v, f = cbox(r / 2, 0, 0.07, r, 0.05, 0.04)
        parts.append((0, rotate_z(v, a), f))
        v, f = cbox(r - 0.025, 0, 0.025, 0.05, 0.05, 0.05)
        parts.append((0, rotate_z(v, a), f))
    parts.append((0, *cylinder(0, 0, 0.09, sh - 0.07, 0.03, segments=8)))
    sd, sw = _u(rng, 0.46, 0.54), _u(rng, 0.46, 0.54)
    parts.append((1, *cbox(0, 0, sh - 0.035, sd, sw, 0.07)))
    parts.append((1, *cbox(-sd / 2 - 0.02, 0, sh + 0.06, 0.04, 0.06, 0.12)))
    parts.append((1, *cbox(-sd / 2 - 0.04, 0, (sh + 0.12 + top) / 2, 0.05, sw - 0.04, top - sh - 0.12)))
    if rng.random() < 0.7:
        for sy in (-1, 1):
            parts.append((1, *cbox(-0.02, sy * (sw / 2 - 0.03), sh + 0.1, 0.04, 0.03, 0.2)))
            parts.append((1, *cbox(0.0, sy * (sw / 2 - 0.03), sh + 0.215, 0.26, 0.06, 0.03)))
    return parts


def folding_chair(rng: np.random.Generator) -> list[Part]:
    """Folding chair: crossed (X) side legs, thin seat and a back panel on the extended rear legs (about 0.45 x 0.43
    x 0.83 m)."""
    w, d = _u(rng, 0.42, 0.48), _u(rng, 0.42, 0.5)
    sh, top = _u(rng, 0.43, 0.46), _u(rng, 0.78, 0.88)
    parts: list[Part] = []
    for sy in (-1, 1):
        y = sy * (w / 2 - 0.015)
        parts.append((0, *bar((d / 2 - 0.02, y, 0.0), (-d / 2 + 0.04, y, top), 0.025, 0.02)))
        parts.append((0, *bar((-d / 2 + 0.02, y, 0.0), (d / 2 - 0.04, y, sh - 0.02), 0.025, 0.02)))
    parts.append((1, *cbox(0, 0, sh - 0.015, d - 0.04, w - 0.05, 0.03)))
    # The back panel follows the slope of the long (rear) legs over their top 0.22 m.
    x_top = -d / 2 + 0.04
    x_low = x_top + (d - 0.06) * 0.22 / top
    parts.append((1, *bar((x_low, 0, top - 0.22), (x_top, 0, top - 0.01), w - 0.05, 0.02)))
    return parts


def lounge_chair(rng: np.random.Generator, length: tuple[float, float] = (1.55, 1.95)) -> list[Part]:
    """Lounge chair (chaise): long low seat on legs with a reclined back at the rear (about 1.75 x 0.68 x 0.84 m with
    the default ``length`` range, m)."""
    length, w = _u(rng, *length), _u(rng, 0.6, 0.75)
    sh, top = _u(rng, 0.3, 0.38), _u(rng, 0.75, 0.95)
    parts = _legs(length, w, 0.12, 0.04, inset=0.05)
    parts.append((1, *cbox(0, 0, (0.12 + sh) / 2, length, w, sh - 0.12)))
    parts.append((1, *bar((-length / 2 + 0.5, 0, sh), (-length / 2 + 0.06, 0, top - 0.04), w, 0.08)))
    return parts


def rocking_chair(rng: np.random.Generator) -> list[Part]:
    """Rocking chair: two curved rockers running front to back under four short legs, a seat, a tall back leaning
    back on two posts, and two arms (about 0.95 x 0.62 x 1.0 m: longer than wide, because of the rockers)."""
    d, w = _u(rng, 0.85, 1.05), _u(rng, 0.55, 0.7)
    sh, top, sd = _u(rng, 0.4, 0.46), _u(rng, 0.92, 1.05), _u(rng, 0.44, 0.52)
    rise, lean = _u(rng, 0.05, 0.09), _u(rng, 0.08, 0.15)  # rocker ends above its lowest point; the back's lean

    def rocker_z(x: float) -> float:  # the rocker's underside (a parabola through the floor contact at x = 0)
        return rise * (2 * x / d) ** 2

    parts: list[Part] = []
    xs = np.linspace(-d / 2, d / 2, 5)
    for sy in (-1, 1):
        y = sy * (w / 2 - 0.02)
        for x0, x1 in zip(xs[:-1], xs[1:]):  # the rocker as four chords, 0.03 m thick, resting on the floor
            parts.append((0, *bar((x0, y, rocker_z(x0) + 0.015), (x1, y, rocker_z(x1) + 0.015), 0.03, 0.03)))
        for sx in (-1, 1):
            x = sx * (sd / 2 - 0.03)
            z0 = rocker_z(x) + 0.03
            parts.append((0, *cbox(x, y, (z0 + sh - 0.04) / 2, 0.035, 0.035, sh - 0.04 - z0)))
        parts.append((1, *bar((-sd / 2 + 0.02, y, sh - 0.04), (-sd / 2 + 0.02 - lean, y, top), 0.035, 0.035)))
        parts.append((1, *bar((sd / 2 - 0.03, y, sh + 0.22), (-sd / 2 + 0.02 - lean * 0.3, y, sh + 0.24), 0.05,
                              0.03)))  # fmt: skip
        parts.append((1, *cbox(sd / 2 - 0.03, y, sh + 0.1, 0.03, 0.03, 0.2)))  # the arm's front support
    parts.append((1, *cbox(0, 0, sh - 0.02, sd, w - 0.06, 0.04)))
    z_back = sh + 0.18
    x_back = -sd / 2 + 0.02 - lean * (z_back - sh + 0.04) / (top - sh + 0.04)
    parts.append((1, *bar((x_back, 0, z_back), (-sd / 2 + 0.02 - lean, 0, top - 0.02), w - 0.08, 0.02)))
    return parts


#: A chair style: (builder, weight, raw categories as (category_mapping index, name)).
ChairStyle = tuple[Callable[[np.random.Generator], list[Part]], float, tuple[tuple[int, str], ...]]
#: Chair styles: name → :data:`ChairStyle`.
CHAIR_STYLES: dict[str, ChairStyle] = {
    "dining": (dining_chair, 0.14, ((7, "chair"), (25, "dining chair"))),
    "armchair": (armchair, 0.42, ((34, "armchair"), (29, "sofa chair"), (227, "easy chair"))),
    "office": (office_chair, 0.08, ((85, "office chair"), (134, "desk chair"), (142, "swivel chair"))),
    "folding": (folding_chair, 0.08, ((581, "folding chair"), (7, "chair"))),
    "lounge": (lounge_chair, 0.28, ((228, "lounge chair"), (488, "chaise"), (427, "recliner"))),
}
#: Chair styles only the realism model's chair mix uses (``Realism.chair_mix``; clean houses never draw them).
REALISM_CHAIR_STYLES: dict[str, ChairStyle] = {
    "rocking": (rocking_chair, 0.0, ((7, "chair"),)),
}


# ---------------------------------------------------------------------------------------------------- others


def table(rng: np.random.Generator, kind: str = "dining") -> list[Part]:
    """Table (``dining``, ``desk`` or ``coffee``): a top on four legs; +x along the long side."""
    if kind == "dining":
        lx, wy, h = _u(rng, 1.4, 2.0), _u(rng, 0.85, 1.0), _u(rng, 0.73, 0.77)
    elif kind == "desk":
        lx, wy, h = _u(rng, 1.2, 1.6), _u(rng, 0.6, 0.75), _u(rng, 0.72, 0.76)
    else:
        lx, wy, h = _u(rng, 0.9, 1.2), _u(rng, 0.5, 0.7), _u(rng, 0.38, 0.46)
    parts = _legs(lx, wy, h - 0.04, 0.06, inset=0.05)
    parts.append((1, *cbox(0, 0, h - 0.02, lx, wy, 0.04)))
    return parts


def stool(rng: np.random.Generator, kind: str = "bar") -> list[Part]:
    """Stool: ``bar`` (round seat on a column and foot ring disc) or ``ottoman`` (upholstered block on feet)."""
    if kind == "ottoman":
        d, w, h = _u(rng, 0.45, 0.7), _u(rng, 0.4, 0.6), _u(rng, 0.38, 0.45)
        parts = _legs(d, w, 0.06, 0.04, inset=0.02)
        parts.append((1, *cbox(0, 0, (0.06 + h) / 2, d, w, h - 0.06)))
        return parts
    r, h = _u(rng, 0.16, 0.2), _u(rng, 0.6, 0.78)
    return [
        (0, *cylinder(0, 0, 0.0, 0.03, r + 0.03, segments=12)),
        (0, *cylinder(0, 0, 0.03, h - 0.05, 0.025, segments=8)),
        (1, *cylinder(0, 0, h - 0.05, h, r, segments=12)),
    ]


def sofa(rng: np.random.Generator) -> list[Part]:
    """Sofa: like an armchair but 1.7-2.4 m wide (+y), with a seat cushion per seat."""
    w, d = _u(rng, 1.7, 2.4), _u(rng, 0.85, 1.0)
    sh, top, arm_w, back_t = _u(rng, 0.4, 0.46), _u(rng, 0.8, 0.95), _u(rng, 0.15, 0.22), _u(rng, 0.18, 0.25)
    parts = _legs(d, w, 0.1, 0.05, inset=0.04)
    parts.append((1, *cbox(0, 0, (0.1 + sh - 0.1) / 2, d, w, sh - 0.2)))
    parts.append((1, *cbox(-d / 2 + back_t / 2, 0, (0.1 + top) / 2, back_t, w, top - 0.1)))
    inner = w - 2 * arm_w
    n = 3 if inner > 1.5 else 2
    for k in range(n):
        y = -inner / 2 + (k + 0.5) * inner / n
        parts.append((1, *cbox((d / 2 - back_t / 2) / 2 + 0.0, y, sh - 0.05, d - back_t, inner / n - 0.01, 0.1)))
    for sy in (-1, 1):
        parts.append((1, *cbox(back_t / 2, sy * (w / 2 - arm_w / 2), (0.1 + sh + 0.2) / 2, d - back_t, arm_w,
                               sh + 0.1)))  # fmt: skip
    return parts


def cabinet(rng: np.random.Generator, tall: bool = False) -> list[Part]:
    """Cabinet: a carcass box with door fronts and handles on its +x face."""
    d, w = _u(rng, 0.42, 0.6), _u(rng, 0.8, 1.6)
    h = _u(rng, 1.6, 2.1) if tall else _u(rng, 0.8, 0.95)
    parts: list[Part] = [(0, *cbox(0, 0, h / 2, d, w, h))]
    n = max(1, round(w / 0.5))
    for k in range(n):
        y = -w / 2 + (k + 0.5) * w / n
        parts.append((1, *cbox(d / 2 + 0.01, y, h / 2, 0.02, w / n - 0.02, h - 0.06)))
        parts.append((1, *cbox(d / 2 + 0.035, y + 0.3 * w / n, h * 0.55, 0.03, 0.02, 0.12)))
    return parts


def bed(rng: np.random.Generator) -> list[Part]:
    """Bed: frame, mattress and a headboard at the -x end (x along the bed's length)."""
    length, w = _u(rng, 2.0, 2.15), _u(rng, 1.4, 1.85)
    hb = _u(rng, 0.9, 1.2)
    return [
        (0, *cbox(0.03, 0, 0.15, length - 0.06, w, 0.3)),
        (1, *cbox(0.04, 0, 0.42, length - 0.1, w - 0.06, 0.24)),
        (0, *cbox(-length / 2 + 0.03, 0, hb / 2, 0.06, w + 0.04, hb)),
    ]


def bench(rng: np.random.Generator) -> list[Part]:
    """Bench (mpcat40 ``seating``): a plank seat on four legs, long along +y."""
    d, w, h = _u(rng, 0.35, 0.45), _u(rng, 1.0, 1.6), _u(rng, 0.43, 0.48)
    parts = _legs(d, w, h - 0.05, 0.05, inset=0.04)
    parts.append((1, *cbox(0, 0, h - 0.025, d, w, 0.05)))
    return parts


def chair_rail(length: float) -> list[Part]:
    """A chair rail (moulding along a wall at seat-back height; mpcat40 ``misc`` despite the name), along +y."""
    return [(0, *cbox(0.01, 0, 0.9, 0.02, length, 0.06))]


# ---------------------------------------------------------------------------------------------------- clutter
# Extra categories of the realism model (mpchair.synth.realism ``clutter`` / ``doors``); never used by clean houses.


def stool_chair(rng: np.random.Generator) -> list[Part]:
    """Stool-like chair (a backless seat on four splayed-in legs, labelled chair in MP3D; about 0.42 x 0.4 x 0.6 m)."""
    w, d, sh = _u(rng, 0.36, 0.46), _u(rng, 0.36, 0.46), _u(rng, 0.45, 0.68)
    parts = _legs(d, w, sh - 0.04, 0.035)
    parts.append((1, *cbox(0, 0, sh - 0.02, d, w, 0.04)))
    parts.append((0, *cbox(0, 0, sh * 0.35, d - 0.07, 0.02, 0.02)))  # a stretcher between the legs
    return parts


def plant(rng: np.random.Generator) -> list[Part]:
    """Potted plant: a pot and a leafy crown of a few overlapping blocks (0.3-0.6 m across, 0.4-1.6 m tall)."""
    r, h = _u(rng, 0.12, 0.25), _u(rng, 0.4, 1.6)
    pot_h = min(0.45, 0.25 * h + 0.1)
    parts: list[Part] = [(0, *cylinder(0, 0, 0.0, pot_h, r, segments=10))]
    for _ in range(int(rng.integers(2, 5))):
        s = _u(rng, 0.6, 1.3) * r * 1.6
        c = rng.uniform(-0.5, 0.5, 2) * r
        z0 = _u(rng, pot_h, pot_h + 0.5 * (h - pot_h))
        parts.append((1, *cbox(c[0], c[1], (z0 + h) / 2, s, s, h - z0)))
    return parts


def shelving(rng: np.random.Generator) -> list[Part]:
    """Open shelving against a wall (back at local -x): two sides, a back, 3-6 shelves and rows of books."""
    d, w, h = _u(rng, 0.28, 0.4), _u(rng, 0.7, 1.5), _u(rng, 0.9, 2.1)
    n = max(2, int(h / 0.36))
    parts: list[Part] = [(0, *cbox(-d / 2 + 0.01, 0, h / 2, 0.02, w, h))]
    for sy in (-1, 1):
        parts.append((0, *cbox(0, sy * (w / 2 - 0.01), h / 2, d, 0.02, h)))
    for k in range(n + 1):
        z = 0.02 + k * (h - 0.04) / n
        parts.append((0, *cbox(0, 0, z, d, w - 0.04, 0.02)))
        if k < n and rng.random() < 0.8:
            bw = _u(rng, 0.2, 0.9) * (w - 0.06)
            bh = min(_u(rng, 0.15, 0.3), (h - 0.04) / n - 0.04)
            y = _u(rng, -(w - 0.06 - bw) / 2, (w - 0.06 - bw) / 2)
            parts.append((1, *cbox(-0.02, y, z + 0.01 + bh / 2, d * 0.75, bw, bh)))
    return parts


def counter(rng: np.random.Generator) -> list[Part]:
    """Kitchen counter against a wall (back at local -x): a base run with a slightly overhanging top (0.9 m high)."""
    d, w, h = _u(rng, 0.58, 0.66), _u(rng, 1.2, 2.6), _u(rng, 0.88, 0.94)
    return [(0, *cbox(-0.02, 0, (h - 0.04) / 2, d - 0.04, w, h - 0.04)), (1, *cbox(0, 0, h - 0.02, d, w + 0.02, 0.04))]


def small_object(rng: np.random.Generator) -> list[Part]:
    """A small object (box, bowl, vase, lamp, basket: mpcat40 ``objects``), 0.06-0.45 m."""
    if rng.random() < 0.4:
        r, h = _u(rng, 0.04, 0.15), _u(rng, 0.06, 0.4)
        return [(0, *cylinder(0, 0, 0.0, h, r, segments=8))]
    sx, sy, sz = _u(rng, 0.08, 0.45), _u(rng, 0.08, 0.4), _u(rng, 0.05, 0.35)
    return [(0, *cbox(0, 0, sz / 2, sx, sy, sz))]


def cushion(rng: np.random.Generator) -> list[Part]:
    """A cushion lying on a seat (0.35-0.55 m square, 0.1-0.16 m thick)."""
    s, t = _u(rng, 0.35, 0.55), _u(rng, 0.1, 0.16)
    return [(0, *cbox(0, 0, t / 2, s, s * _u(rng, 0.85, 1.0), t))]


def door_leaf(width: float, height: float) -> list[Part]:
    """A door leaf hinged at the local origin, extending along +x (``width``), 0.04 m thick, with a handle."""
    return [(0, *cbox(width / 2, 0, height / 2, width, 0.04, height)),
            (0, *cbox(width - 0.08, 0, 1.0, 0.03, 0.14, 0.03))]  # fmt: skip
