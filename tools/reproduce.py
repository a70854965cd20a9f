"""``make reproduce``: the Sparse PointPillars Matterport-Chair experiment end to end (``detector.reproduce.cli``)."""

from detector.reproduce.cli import main

raise SystemExit(main())
