"""``make reproduce``: the Sparse PointPillars Matterport-Chair experiment end to end (``reproduction.cli``)."""

from reproduction.cli import main

raise SystemExit(main())
