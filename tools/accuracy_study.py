"""``make accuracy-study``: the accuracy study, one session's share at a time (``reproduction.study_cli``)."""

from reproduction.study_cli import main

raise SystemExit(main())
