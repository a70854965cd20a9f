"""Writing the dataset: one frame at a time (``frame``: viewpoint, labels, scan, KITTI files, frame record), the
records a dataset holds about itself (``manifest``: ``FrameRecord`` per frame, the ``Manifest``, their readers), the
houses of a run (``houses``: ``RunHouses``, read and hashed once for ``generate`` and ``stream``), the
train/val/test splits (``splits``), and the orchestration behind ``mpchair generate`` (``generate``: seeds, worker
processes, shards, resume after SIGKILL, progress, the manifest written last; ``job``: the steps it shares with
``mpchair stream``). Scans and boxes are in the sensor frame (x forward, y left, z up, metres), poses map sensor →
world (Matterport, z up, metres).

The package imports none of its modules, so that reading a manifest (``mpchair.dataset.manifest``, for ``mpchair
stats`` / ``view``) does not load the raycaster: import ``mpchair.dataset.generate`` for ``generate``.
"""
