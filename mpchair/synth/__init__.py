"""Synthetic houses in the exact Matterport3D release and habitat formats: procedural multi-room homes (doors, windows,
stairs, holes) furnished with chairs of five styles and non-chair distractors, written as
``v1/scans/<id>/house_segmentations`` or habitat's ``mp3d/<id>/`` (with a navmesh built from the floor: ``navmesh.py``),
extracted or zipped, so the one reader in :mod:`mpchair.matterport` serves real and synthetic data. The construction
record (:class:`SyntheticHouse`) carries the ground-truth objects and aligned boxes the reader must reproduce.
:class:`Realism` (``realism.py``) sets how much a house looks like a Matterport3D reconstruction (noise, waves, holes,
label bleed, fragments, clutter: ``artifacts.py``); ``CLEAN`` gives the plain procedural houses, ``DEFAULT`` the
calibrated ones.
"""

from mpchair.synth.house import (
    SyntheticHouse,
    SynthObject,
    plan_houses,
    subdivide_house,
    synthesize_house,
    write_house,
    write_synthetic_houses,
)
from mpchair.synth.realism import CLEAN, DEFAULT, Realism, realism_preset

__all__ = [
    "CLEAN",
    "DEFAULT",
    "Realism",
    "SynthObject",
    "SyntheticHouse",
    "plan_houses",
    "realism_preset",
    "subdivide_house",
    "synthesize_house",
    "write_house",
    "write_synthetic_houses",
]
