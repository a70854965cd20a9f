"""Each sparse conv kind in its one-GEMM form against its rulebook form and the ``auto`` pick (docs/sparse.md,
"Compute"): the "forms" rows of ``tools/bench_sparse.py``.

Synthetic layers (:data:`FORM_CASES`: the SubM, 2x2 and 9x9 stride-2 down and s = 2 / 4 transposed conv shapes the
Matterport model runs) on clustered and uniform sites (:mod:`detector.sparse.synthetic`), eval mode, ``no_grad``, an
inference workspace; the SubMs also forward + backward (``*_train``). On real frames, the whole sparse backbone of
``mpchair_sparse.yaml`` with every conv of one kind forced to each form. Random weights (the timings do not depend on
them); the forms interleaved (:func:`detector.bench.timing.time_calls`); times in ms.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from detector.bench.timing import time_calls
from detector.checkpoint import load_model
from detector.config import CONFIG_DIR, load_experiment
from detector.data.experiment import load_eval_frames
from detector.sparse import SparseConv2d, SparseConvTranspose2d, SparseTensor, SubMConv2d, Workspace
from detector.sparse.indices import down_table
from detector.sparse.synthetic import clustered_sites, uniform_sites

#: The forms a sparse conv computes in (``auto``: the layer's own pick).
ALGORITHMS = ("gemm", "rulebook", "auto")
#: (kind, grid, density, in, out, kernel, stride) of the conv shapes the Matterport model runs: SubMs at block 1
#: (384 x 256, 64 ch) and block 3 (96 x 64, 256 ch), the 2x2 and the 9x9 stride-2 down-convs on the pillar grid, the
#: neck's s = 2 and s = 4 transposed convs onto the block-1 set.
FORM_SHAPES = (
    ("subm", (384, 256), 0.013, 64, 64, 3, 1),
    ("subm", (96, 64), 0.02, 256, 256, 3, 1),
    ("down", (768, 512), 0.0075, 64, 64, 2, 2),
    ("wide_down", (768, 512), 0.0075, 64, 64, 9, 2),
    ("up", (384, 256), 0.013, 128, 128, 2, 2),
    ("up", (384, 256), 0.013, 256, 128, 4, 4),
)
#: (kind, grid, pattern, density, in, out, kernel, stride): every shape on clustered, then on uniform sites.
FORM_CASES = tuple((kind, grid, pattern, *rest) for kind, grid, *rest in FORM_SHAPES
                   for pattern in ("clustered", "uniform"))


def make_sites(pattern: str, shape: tuple[int, int], density: float, seed: int) -> torch.Tensor:
    """(P, 3) int64 ``[0, iy, ix]`` sites of a ``shape`` (ny, nx) grid at ``density``: ``clustered`` (blobs and wall
    segments, like real scans) or ``uniform``."""
    return (clustered_sites if pattern == "clustered" else uniform_sites)(shape, density, seed=seed)


def bench_forms(repeats: int) -> list[dict[str, object]]:
    """One row per :data:`FORM_CASES` entry: ``{"case", "active", "fill", "timings"}``, timings per form (and per
    SubM ``gemm_train`` / ``rulebook_train``) as :func:`detector.bench.timing.time_calls` gives them."""
    rows = []
    for kind, shape, pattern, density, cin, cout, k, s in FORM_CASES:
        coords = make_sites(pattern, shape, density, seed=5)
        ws = Workspace()
        x = SparseTensor(torch.randn(coords.shape[0], cin).relu(), coords, shape, 1, workspace=ws, origin="input")
        if kind == "up":  # the coarse input is the site set a down-conv of the target gives
            t = down_table(coords, shape, s)
            coarse = SparseTensor(torch.randn(t.out_coords.shape[0], cin), t.out_coords, t.out_shape, 1,
                                  workspace=ws, origin="coarse")
            mods = {a: SparseConvTranspose2d(cin, cout, k, s, algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, c=coarse, x=x: m(c, x)) for a, m in mods.items()}
            fill = float((t.in_rows.numel()) / max(1, t.out_coords.shape[0] * s * s))
        elif kind == "subm":
            mods = {a: SubMConv2d(cin, cout, k, indice_key="k", algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, x=x: m(x)) for a, m in mods.items()}
            fill = mods["auto"].table(x).fill
        else:
            mods = {a: SparseConv2d(cin, cout, k, s, algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, x=x: m(x)) for a, m in mods.items()}
            fill = None
        for m in mods.values():
            m.eval().load_state_dict(mods["auto"].state_dict())
        with torch.no_grad():
            r = time_calls(fns, repeats)
        if kind == "subm":  # training: forward + backward of the layer (no workspace), input gradient included
            xt = SparseTensor(x.features.clone().requires_grad_(True), coords, shape, 1)
            g = torch.randn(coords.shape[0], cout)
            r.update(time_calls({f"{a}_train": (lambda m=mods[a], xt=xt, g=g: m(xt).features.backward(g))
                                 for a in ("gemm", "rulebook")}, repeats))
        rows.append({"case": f"{kind} {k}x{k}/s{s} {cin}->{cout} {shape[0]}x{shape[1]} {pattern} {100 * density:.2f}%",
                     "active": int(coords.shape[0]), "fill": None if fill is None else round(fill, 3), "timings": r})
    return rows


def bench_forms_real(repeats: int, data: Path, frames: int) -> list[dict[str, object]]:
    """The Matterport sparse backbone on the first ``frames`` test frames of ``data`` (``mpchair_sparse.yaml``, random
    weights, workspace) with every conv of one kind forced to each form: one row per kind, whole-backbone ms per
    frame."""
    cfg = load_experiment(CONFIG_DIR / "mpchair_sparse.yaml")
    model = load_model(cfg, None, torch.device("cpu"), seed=0).eval()
    model.workspace = Workspace()
    with torch.no_grad():
        inputs = [model.pillar_net(model.voxelize([torch.from_numpy(f.points)]))
                  for f in load_eval_frames(cfg, data, "test", frames)]
    rows = []
    for kind, types in (("subm", SubMConv2d), ("down", SparseConv2d), ("up", SparseConvTranspose2d)):
        mods = [m for m in model.modules() if isinstance(m, types)]

        def run(a: str, mods: list[nn.Module] = mods) -> None:
            for m in mods:
                m.algorithm = a
            for f, c in inputs:
                model.backbone_neck(model.feature_net(f, c, 1))

        with torch.no_grad():
            r = time_calls({a: (lambda a=a: run(a)) for a in ALGORITHMS}, repeats)
        for v in r.values():  # per frame
            for key in ("min_ms", "median_ms", "cpu_min_ms"):
                v[key] /= len(inputs)
        rows.append({"case": f"backbone on {len(inputs)} real frames of {data}, every {kind} conv forced",
                     "timings": r})
    return rows


def format_forms(title: str, rows: list[dict[str, object]]) -> str:
    """The rows under a ``## title`` heading: per form wall min / median, CPU min and the rulebook / this CPU ratio."""
    lines = [f"\n## {title}"]
    for row in rows:
        t: dict[str, dict[str, float]] = row["timings"]  # type: ignore[assignment]
        extra = {k: v for k, v in row.items() if k not in ("case", "timings")}
        lines.append(f"{row['case']}  {extra}")
        for k, v in t.items():
            ratio = t["rulebook_train" if k.endswith("_train") else "rulebook"]["cpu_min_ms"] / v["cpu_min_ms"]
            lines.append(f"  {k:10s} wall min {v['min_ms']:8.3f} median {v['median_ms']:8.3f}  cpu min "
                         f"{v['cpu_min_ms']:8.3f} ms   rulebook / this (cpu) {ratio:5.2f}x")
    return "\n".join(lines)
