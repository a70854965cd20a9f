"""The shared floor's plumbing, imported by both stacks and importing neither: ``errors`` (``InputError``,
``RunError``), ``atomic`` (temp file + rename for every write), ``lock`` (one writer per output folder), ``config``
(YAML into frozen dataclasses), ``jit`` (numba with an on-disk cache), ``heap`` (glibc malloc tuning for frame
makers), ``cpu`` (the CPU's instruction-set flags) and ``clitools`` (one ``error:`` line and exit 2 for bad input)."""
