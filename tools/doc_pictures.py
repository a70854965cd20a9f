"""Regenerate the pictures and the numbers of ``docs/stats.md`` (``reproduction.doc_pictures``)."""

from reproduction.doc_pictures import main

raise SystemExit(main())
