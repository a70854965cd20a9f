"""``python -m detector`` (and ``torchrun -m detector``) runs the detector CLI."""

from detector.cli import main

main()
