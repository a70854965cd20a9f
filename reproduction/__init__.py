"""The paper's experiment, on a floor of its own above both stacks: ``make reproduce`` and ``make reproduce-stream``
(end to end, CPU-sized), the accuracy study, the GPU check and the pictures of ``docs/stats.md``.

It drives the ``mpchair`` and ``detector`` commands as subprocesses (each command line printed, run and logged),
reads their output files through the one definition next to each writer, and writes the clone's ``docs/`` from them.
Neither stack imports it (``tests/test_layout.py``). It runs in a clone only (:mod:`.checkout`); its command lines
raise :class:`~mpchair.core.errors.InputError` through :func:`mpchair.core.clitools.run_script`, and the scripts of
``tools/`` that start them (``reproduce.py``, ``reproduce_stream.py``, ``accuracy_study.py``, ``device_check.py``,
``doc_pictures.py``) only import and call their ``main``.

    checkout  the clone this package runs in (found from the package's own location), refused elsewhere
    scales    the sizes of each scale (houses, frames, epochs, bench trials) and the bf16 detection
    runner    runs and logs command lines (``commands.log``)
    steps     each step's command lines and the files that mark it done (``step_outputs``)
    ablations the ablation steps: their benches at both geometries, their opt-in trainings and evals
    deploy    the deploy step: the trained models exported, evaluated and timed per runtime and precision
    results   typed readers of every file the steps write that the report reads
    training  what the work folder's trainings were: schedules, precision, seconds
    report    ``docs/results.md`` from those records (``report_runtime``: training time, reference head, density
              curve; ``report_ablations``: the ablations' runtime and AP)
    status    ``--status``: where a work folder stands
    estimate  how long the steps still to run take on this machine, printed before they start (the record's measured
              command times scaled to the scale's sizes and to this machine's GEMM probe)
    record    the run record in ``docs/results-data/`` (a later session rewrites the report or adds steps from it)
    cli       ``main(argv)`` of ``tools/reproduce.py``
    stream/   the streaming reproduction (``tools/reproduce_stream.py``, ``docs/streaming.md``)
    study, study_report, study_cli
              the accuracy study (``tools/accuracy_study.py``, ``docs/results-data/accuracy``)
    device_check/
              the Python side of the GPU check (``tools/device_check.sh``)
    doc_pictures
              the pictures and numbers of ``docs/stats.md`` (``tools/doc_pictures.py``)
"""
