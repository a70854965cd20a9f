"""What a dataset holds, as numbers and pictures: ``stats`` (pseudoimage density *D*, box statistics; ``mpchair
stats``) and ``render`` (PNGs of frames, houses and the statistics; ``mpchair view``, ``view-house``)."""
