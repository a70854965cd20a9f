"""Where ONNX Runtime spends its time in an exported sparse graph: node counts and per-node profile shares.

Exports the all-sparse model of ``--config`` (random weights, BatchNorm randomised by
``detector.bench.spconv_peer.randomise_batchnorm_``) with ``detector.deploy.export.write_onnx``, prints its node count
by op type as exported and after ONNX Runtime's optimiser (``ORT_ENABLE_ALL``), then runs ``--frames`` synthetic frames
(``detector.sparse.synthetic.clustered_sites`` at ``--density``, random features) ``--repeats`` times with ONNX
Runtime's profiling on and prints each op type's and the top nodes' share of the kernel time, each node's time the
minimum over the repeats of the same frame (a node preempted in one repeat is not counted). Shares, not speed:
``detector bench --runtime`` times the deployed models. Asserts nothing.
docs/measurements/export-graph-analysis-2026-12-07.md quotes it.

Usage: ``python tools/profile_export_graph.py [--config mpchair_sparse] [--head dense] [--density 0.008]
[--frames 4] [--repeats 4] [--threads 1] [--top 8] [--out DIR]``
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sys
import tempfile
from pathlib import Path


def _counts(graph) -> str:
    c = collections.Counter(n.op_type for n in graph.node)
    return f"{len(graph.node)}: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items(), key=lambda kv: (-kv[1], kv[0])))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="mpchair_sparse", help="an all-sparse config (packaged name or YAML path)")
    p.add_argument("--head", choices=("dense", "sparse_exact"), default="dense")
    p.add_argument("--density", type=float, default=0.008, help="active pillars / cells of the pseudo-image")
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--repeats", type=int, default=4)
    p.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads")
    p.add_argument("--top", type=int, default=8, help="nodes listed")
    p.add_argument("--out", type=Path, default=None, help="keep the ONNX files and the profile here")
    args = p.parse_args(argv)
    if not (0 < args.density < 1 and args.frames >= 1 and args.repeats >= 1 and args.threads >= 1):
        p.error("--density must be in (0, 1); --frames, --repeats and --threads >= 1")

    import onnx
    import onnxruntime as ort
    import torch

    from detector.bench.spconv_peer import randomise_batchnorm_
    from detector.config import config_file, load_experiment
    from detector.deploy.export import graph_module, write_onnx
    from detector.deploy.runtimes import onnxruntime_options
    from detector.deploy.sparse_graph import build_tables
    from detector.models import build_model
    from detector.sparse.synthetic import clustered_sites

    cfg = load_experiment(config_file(args.config))
    torch.manual_seed(0)
    model = build_model(dataclasses.replace(cfg.model, head=args.head)).eval()
    randomise_batchnorm_(model, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"{args.head}.onnx"
        with torch.no_grad():
            write_onnx(model, path)
        graph = graph_module(model)
        feeds = []
        for s in range(args.frames):
            coords = clustered_sites(model.output_shape, args.density, seed=s)
            feats = torch.rand(coords.shape[0], model.pillar_encoder.out_channels,
                               generator=torch.Generator().manual_seed(s))
            feeds.append({k: v.numpy() for k, v in build_tables(graph.spec, feats, coords).inputs.items()})
        o = onnxruntime_options(args.threads)  # the bench's session, plus the profile and the optimised graph
        o.optimized_model_filepath = str(out / f"{args.head}.optimized.onnx")
        o.enable_profiling, o.profile_file_prefix = True, str(out / f"{args.head}-profile")
        session = ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"])
        print(f"{args.config}, {args.head} head, {model.output_shape[0]} x {model.output_shape[1]}, density "
              f"{args.density}: {[int(f['features'].shape[0]) for f in feeds]} pillars")
        print("exported nodes", _counts(onnx.load(str(path)).graph))
        print("ONNX Runtime optimised nodes", _counts(onnx.load(o.optimized_model_filepath).graph))
        for _ in range(args.repeats):
            for f in feeds:
                session.run(None, f)
        events = json.loads(Path(session.end_profiling()).read_text())
    runs, cur = [], []
    for e in events:  # a run's node events come before its model_run event
        if e.get("cat") == "Session" and e["name"] == "model_run":
            runs.append(cur)
            cur = []
        elif e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            cur.append((e["name"][: -len("_kernel_time")], e["args"]["op_name"], e["dur"]))
    best: dict[tuple[int, str], float] = {}
    op_of: dict[str, str] = {}
    for k, run in enumerate(runs):
        for name, op, d in run:
            op_of[name] = op
            best[k % args.frames, name] = min(best.get((k % args.frames, name), float("inf")), d)
    by_op: collections.Counter = collections.Counter()
    by_node: collections.Counter = collections.Counter()
    for (_, name), d in best.items():
        by_op[op_of[name]] += d
        by_node[name] += d
    total = sum(by_node.values()) or 1.0
    print("share of kernel time by op type (each node's minimum over the repeats of a frame):")
    for k, v in by_op.most_common():
        print(f"  {k:24s} {100 * v / total:5.1f} %")
    print(f"top {args.top} nodes:")
    for k, v in by_node.most_common(args.top):
        print(f"  {k:64s} {op_of[k]:12s} {100 * v / total:5.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
