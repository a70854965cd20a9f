"""``make accuracy-study``: the accuracy study, one session's share at a time (``detector.reproduce.study_cli``)."""

from detector.reproduce.study_cli import main

raise SystemExit(main())
