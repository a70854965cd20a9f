"""``make reproduce-stream``: streaming AP of dense vs sparse PointPillars (``reproduction.stream.cli``)."""

from reproduction.stream.cli import main

raise SystemExit(main())
