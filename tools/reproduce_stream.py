"""``make reproduce-stream``: streaming AP of dense vs sparse PointPillars (``detector.reproduce.stream.cli``)."""

from detector.reproduce.stream.cli import main

raise SystemExit(main())
