"""The sparse backbone + neck against its limit (issue 49, target 2): its exact multiply-adds per frame, the rate
oneDNN's dense convolution reaches on this machine, the measured sparse time, their ratio, and where the time goes
per op kind, in one run (``detector.bench.limit``; docs/sparse.md, "The limit").

    PYTHONPATH=. .venv/bin/python tools/bench_limit.py --threads 1,2 --repeats 7 --profile-repeats 3 \\
        [--config mpchair_sparse] [--checkpoint W] [--data DATASET --split test] [--frames 8] [--json-out FILE]

Run it on a quiet machine: on a busy one the numbers are not the instrument's.
"""

from detector.bench.limit import main

if __name__ == "__main__":
    raise SystemExit(main())
