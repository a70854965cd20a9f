"""The GPU check (``tools/device_check.sh``, issue 32, "The GPU path, tested"): the Python side of the script, one
subcommand per job (``python tools/device_check.py SUBCOMMAND``, :mod:`.cli`).

    step NAME [--stdout FILE] [--timeout S] -- CMD ...   run one step of the check, record RESULTS/steps/NAME.json
    machine --device D --out FILE                        the GPU(s), driver, CUDA, torch and autocast dtype as JSON
    configs --out DIR [--tiny]                           the six experiment YAMLs the check runs (EXPERIMENTS)
    tests --junit XML --out FILE                         pytest's JUnit XML as JSON counts and cases
    train --config C --data D --run DIR --device D --precision fp32|autocast --steps N --out FILE
                                                         one ``detector train`` run: steps/s and peak memory
    ddp --config C --data D --run DIR --device D --steps N --out FILE
                                                         a 2-process torchrun ``detector train`` (or why not)
    report --results DIR --out DIR                       summary.json + summary.md: every result, the paper beside

Every model run goes through the ``detector`` command line (``detector train`` in this process, so that the peak
memory of the run can be read here; the rest as subprocesses). Steps run against a deadline: the shell script exports
``DEVICE_CHECK_DEADLINE`` (Unix seconds); a step that would start past it is recorded as skipped, and a running step
is stopped at it, so the whole check keeps to its time budget. Files are written with :mod:`mpchair.core.atomic`.

    files     the result files: one JSON writer and reader
    step      one step of the check as a subprocess, against the check's deadline
    jobs      machine, configs, tests, train, ddp: each writes one result file
    report    summary.json and summary.md, with the paper's Desktop runtimes beside ours
    cli       the subcommands (each imports only its own job: ``step`` never loads torch)
"""
