"""The Sparse PointPillars paper's published figures: the one place they are written down.

Every report, figure and tool that compares with the paper reads its numbers from here (``tests/test_paper.py`` fails
on a copy elsewhere). Source: ``sparse-pointpillars.tex`` (the paper's LaTeX); each entry names its table or section.
Sections are numbered as printed: I Introduction, II Related Work, III the new pipeline, IV Theoretical Analysis,
V Empirical Evaluation (V-A Matterport-Chair, V-B KITTI). Tables: I operation counts (``opstable``), II
Matterport-Chair runtimes (``customtable``), III KITTI AP (``perfbaselinesparse``), IV KITTI runtimes (``runtimes``).

Units: densities are fractions of the padded pseudoimage (non-empty pillars / (W x H)); AP in percent; times in
milliseconds per frame (mean and standard deviation over the paper's trials, batch 1). Models are keyed by this
project's backbone names (``dense`` = PointPillars, ``sparse`` = Sparse PointPillars, ``sparse1_dense23``,
``sparse12_dense3``, ``sparse_wide_down``: the paper's one Sparse+WideConv row, which came from its released code).

It lives on the shared floor so both ``mpchair stats`` and the detector's reports can import it; it imports nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType


@dataclass(frozen=True)
class Density:
    """A dataset's pseudoimage density D over its test frames (fraction of the padded W x H canvas)."""

    median: float
    min: float
    max: float

    def to_json(self) -> dict[str, float]:
        """``{"median", "min", "max"}`` in that order (``mpchair stats --json``'s ``paper`` entries)."""
        return {"median": self.median, "min": self.min, "max": self.max}


@dataclass(frozen=True)
class Timed:
    """One runtime cell: mean and standard deviation, milliseconds per frame."""

    mean_ms: float
    std_ms: float


@dataclass(frozen=True)
class ComponentTimes:
    """One row of Table II / IV: the paper's timing components, in its column order."""

    to_device: Timed
    feature_extract: Timed
    feature_net: Timed
    backbone: Timed
    head: Timed
    bbox_extract: Timed
    total: Timed

    def items(self) -> tuple[tuple[str, Timed], ...]:
        """``(component, Timed)`` pairs in the table's column order."""
        return tuple((f.name, getattr(self, f.name)) for f in fields(self))

    def to_json(self) -> dict[str, list[float]]:
        """``{component: [mean_ms, std_ms]}`` in column order."""
        return {name: [t.mean_ms, t.std_ms] for name, t in self.items()}


@dataclass(frozen=True)
class Levels:
    """An AP figure at KITTI's three difficulty levels (percent, or percentage points for a delta)."""

    easy: float
    moderate: float
    hard: float


@dataclass(frozen=True)
class KittiAP:
    """One model's column group of Table III: BEV and 3D AP (PointPillars absolute, every other model its delta)."""

    bev: Levels
    ap_3d: Levels


@dataclass(frozen=True)
class MatterportAP:
    """Section V-A: PointPillars' AP on Matterport-Chair (IoU 0.5, one level) and Sparse PointPillars' delta to it."""

    dense_bev: float
    dense_3d: float
    sparse_bev_delta: float
    sparse_3d_delta: float


def _row(*cells: tuple[float, float]) -> ComponentTimes:
    return ComponentTimes(*(Timed(mean, std) for mean, std in cells))


#: Section IV: median (min, max) D of Matterport-Chair's test data.
MATTERPORT_CHAIR_DENSITY = Density(median=0.00750, min=0.00029, max=0.01679)
#: Section IV: median (min, max) D of KITTI's test data.
KITTI_DENSITY = Density(median=0.02459, min=0.013321, max=0.03899)
#: Section IV (Table I at the median D): the sparse Backbone performs at least this fraction fewer convolutions.
MATTERPORT_CHAIR_FEWER_CONVOLUTIONS = 0.79
KITTI_FEWER_CONVOLUTIONS = 0.50

#: Section V-A: the Matterport-Chair AP (BEV 84.09, 3D 80.66; sparse -6.04 / -4.61 points).
MATTERPORT_CHAIR_AP = MatterportAP(dense_bev=84.09, dense_3d=80.66, sparse_bev_delta=-6.04, sparse_3d_delta=-4.61)
#: Section V-A: Sparse PointPillars trains this many times faster (whole run, a GPU at 768 x 512) ...
SPARSE_TRAIN_SPEEDUP = 1.8
#: ... despite this many times the epochs (25 % more: 50 more epochs).
SPARSE_EPOCH_RATIO = 1.25
#: Section V-A: cores of the robot's CPU (a Fetch Freight's Intel i5-4590S).
ROBOT_CORES = 4

#: Table II (Matterport-Chair, 768 x 512): platform -> model -> component times. Platforms: ``desktop`` (AMD Ryzen 7
#: 3700X + NVIDIA 2080 Ti), ``jetson_30w`` / ``jetson_10w`` (Jetson Xavier, 8 cores at 30 W / 2 cores at 10 W),
#: ``robot`` (the Fetch Freight's 4-core CPU).
TABLE_II: Mapping[str, Mapping[str, ComponentTimes]] = MappingProxyType({
    "desktop": MappingProxyType({
        "dense": _row((0.072, 0.001), (1.783, 0.010), (0.390, 0.005), (2.512, 0.017), (0.199, 0.001),
                      (15.198, 0.145), (20.154, 0.143)),
        "sparse": _row((0.073, 0.001), (1.747, 0.015), (0.130, 0.002), (6.633, 0.038), (0.218, 0.002),
                       (4.854, 0.010), (13.655, 0.060)),
    }),
    "jetson_30w": MappingProxyType({
        "dense": _row((0.657, 0.056), (13.526, 0.195), (4.509, 0.074), (17.335, 0.163), (1.586, 0.016),
                      (126.374, 0.227), (163.987, 0.485)),
        "sparse": _row((0.602, 0.007), (13.451, 0.076), (1.341, 0.030), (43.935, 0.176), (2.199, 0.012),
                       (27.054, 0.139), (88.584, 0.349)),
    }),
    "jetson_10w": MappingProxyType({
        "dense": _row((2.128, 0.422), (28.340, 0.098), (6.907, 0.094), (14.557, 0.292), (1.511, 0.009),
                      (407.499, 0.302), (460.941, 0.246)),
        "sparse": _row((2.163, 0.106), (28.813, 0.047), (1.728, 0.007), (60.233, 0.076), (2.385, 0.004),
                       (62.169, 0.073), (157.492, 0.199)),
    }),
    "robot": MappingProxyType({
        "dense": _row((1.531, 0.216), (43.073, 0.482), (29.237, 0.319), (879.225, 6.116), (115.363, 1.065),
                      (13.706, 0.064), (1082.135, 6.692)),
        "sparse": _row((1.383, 0.111), (41.073, 0.994), (0.313, 0.004), (66.045, 0.409), (114.911, 1.171),
                       (13.012, 0.171), (236.737, 2.491)),
    }),
})

#: Table III (KITTI Car, 16 cm pillars, IoU 0.7): PointPillars' AP and every other model's delta to it.
TABLE_III: Mapping[str, KittiAP] = MappingProxyType({
    "dense": KittiAP(bev=Levels(90.75, 89.79, 89.48), ap_3d=Levels(82.30, 80.34, 79.11)),
    "sparse": KittiAP(bev=Levels(-5.71, -6.53, -4.98), ap_3d=Levels(-8.82, -7.83, -9.16)),
    "sparse1_dense23": KittiAP(bev=Levels(-5.25, -5.44, -3.73), ap_3d=Levels(-7.62, -7.36, -8.85)),
    "sparse12_dense3": KittiAP(bev=Levels(-5.54, -5.89, -5.60), ap_3d=Levels(-8.88, -7.71, -9.27)),
    "sparse_wide_down": KittiAP(bev=Levels(-6.89, -7.24, -9.25), ap_3d=Levels(-11.1, -11.57, -13.69)),
})

#: Table IV (KITTI, 504 x 440, the desktop of Table II): model -> component times.
TABLE_IV: Mapping[str, ComponentTimes] = MappingProxyType({
    "dense": _row((0.064, 0.000), (2.375, 0.010), (0.303, 0.004), (2.358, 0.027), (0.204, 0.002), (9.105, 0.030),
                  (14.410, 0.033)),
    "sparse": _row((0.064, 0.000), (2.330, 0.009), (0.133, 0.002), (7.578, 0.038), (0.244, 0.004), (3.877, 0.010),
                   (14.226, 0.056)),
    "sparse1_dense23": _row((0.064, 0.000), (2.341, 0.011), (0.134, 0.002), (7.394, 0.049), (0.231, 0.003),
                            (4.437, 0.013), (14.602, 0.068)),
    "sparse12_dense3": _row((0.064, 0.000), (2.359, 0.011), (0.134, 0.002), (7.803, 0.050), (0.236, 0.002),
                            (4.406, 0.018), (15.001, 0.080)),
    "sparse_wide_down": _row((0.066, 0.001), (2.356, 0.015), (0.137, 0.002), (17.286, 0.071), (0.242, 0.007),
                             (6.184, 0.038), (26.270, 0.124)),
})
