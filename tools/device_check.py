"""``tools/device_check.sh``'s Python side: the GPU check's subcommands (``reproduction.device_check.cli``)."""

from reproduction.device_check.cli import main

raise SystemExit(main())
