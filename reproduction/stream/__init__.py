"""``make reproduce-stream`` as a package: streaming AP of dense vs sparse PointPillars on a robot driving through the
test houses, with latencies measured on this CPU (``docs/streaming.md``).

    sweep     the scales, the (speed, rate) points of the sweep and their stream folders
    steps     each step's ``mpchair stream`` / ``detector stream-eval`` command lines
    results   typed readers of the stream-eval summaries and stream metadata the report reads
    report    the results section of docs/streaming.md (table, curves, crossover speed) between its markers
    cli       ``main(argv)`` of ``tools/reproduce_stream.py``
"""
