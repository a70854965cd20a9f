"""``make reproduce`` and ``make reproduce-stream`` as a package: the paper's experiment end to end, CPU-sized.

It drives the ``mpchair`` and ``detector`` commands as subprocesses (each command line printed, run and logged) and
writes its reports from their output files; it imports only the floor of ``mpchair`` (``mpchair.core``,
``mpchair.kitti``) and ``detector``. ``tools/reproduce.py`` and ``tools/reproduce_stream.py`` are its front-ends.

    scales    the sizes of each scale (houses, frames, epochs, bench trials) and the bf16 detection
    runner    runs and logs command lines (``commands.log``)
    steps     each step's command lines and the files that mark it done (``step_outputs``)
    ablations the ablation steps: their benches at both geometries, their opt-in trainings and evals
    results   typed readers of every file the steps write that the report reads
    training  what the work folder's trainings were: schedules, precision, seconds
    report    ``docs/results.md`` from those records (``report_runtime``: training time, reference head, density
              curve; ``report_ablations``: the ablations' runtime and AP)
    status    ``--status``: where a work folder stands
    estimate  how long the steps still to run take on this machine, printed before they start (the record's measured
              command times scaled to the scale's sizes and to this machine's GEMM probe)
    cli       ``main(argv)`` of ``tools/reproduce.py``
    stream/   the streaming reproduction (``tools/reproduce_stream.py``, ``docs/streaming.md``)
"""
