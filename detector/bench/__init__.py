"""The runtime benchmark (``detector bench``): the paper's per-component timings of dense and sparse PointPillars.

- :mod:`detector.bench.timing`: the components, their titles, and the stamps around one frame's stages;
- :mod:`detector.bench.result`: the result as one typed record (:class:`~detector.bench.result.BenchResult`), the
  one definition of ``detector bench --json``'s file (``to_json`` / ``from_json``);
- :mod:`detector.bench.peer`: Open3D-ML's own PointPillars as a peer row (imports ``timing``);
- :mod:`detector.bench.run`: the protocol (warm-up, interleaved trials, back to back), the rows of every model x
  runtime x precision (deployed ones from :mod:`detector.deploy`) and the result (imports ``timing``, ``peer`` and
  ``result``);
- :mod:`detector.bench.budget`: ``--rate``, each row alone at a fixed sensor rate: CPU share, deadline misses,
  latency, peak memory (imports ``run``);
- :mod:`detector.bench.report`: the result as the paper's tables (imports ``timing`` and ``result``; reads only the
  result);
- :mod:`detector.bench.reference_head` (the total time with the reference's head layout),
  :mod:`detector.bench.density` (the backbone ratio against density D) and :mod:`detector.bench.sparse_ratios` (dense
  vs sparse layers, backbone, end to end and training step, with :mod:`detector.bench.conv_forms`): benches of their
  own, for the tools ``bench_reference_head``, ``bench_density`` and ``bench_sparse`` (``reference_head`` imports
  ``timing`` and ``run``, ``density`` :mod:`detector.opcount`, ``sparse_ratios`` and ``conv_forms`` ``timing``;
  nothing here imports them).

The modules import each other directly, in that one direction; this file only re-exports the names callers use. The
machine a result describes is a :class:`detector.device.Machine` record.
"""

from detector.bench.report import format_table, machine_line, ratio_rows
from detector.bench.result import BenchResult
from detector.bench.run import BenchModel, default_name, run_bench
from detector.bench.timing import COMPONENTS, SHARED, TITLES, time_frame, time_shared

__all__ = ["COMPONENTS", "SHARED", "TITLES", "BenchModel", "BenchResult", "default_name", "format_table",
           "machine_line", "ratio_rows", "run_bench", "time_frame", "time_shared"]
