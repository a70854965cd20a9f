"""Load an mpchair dataset (or any KITTI-layout folder) with Open3D-ML's own KITTI reader.

Open3D-ML's ``open3d.ml.datasets.KITTI`` reads our files unchanged (calib, label_2, velodyne), but two things in it are
hard-wired to the KITTI benchmark: its split reader crops points to a fixed 375 x 1242 image window (our virtual camera
is 1024 x 1024, so most points would be cut), and its box class renames every type outside KITTI's list (``Chair``
included) to ``DontCare``. :func:`open3d_ml_dataset` returns a subclass that keeps the full scan (every mpchair point
lies in the camera anyway), keeps the label file's class names, and takes the split lists from ``ImageSets``.
Everything else (label parsing, calibration, box conventions) is Open3D-ML's.

Needs Open3D with its ML part: ``pip install 'open3d-cpu[ml]'`` (Linux x86-64) or ``'open3d[ml]'``; the ``open3d``
extra of this project installs it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mpchair.core.errors import InputError
from mpchair.kitti.imagesets import read_imageset
from mpchair.kitti.layout import imageset_path

#: Split names of Open3D-ML (``get_split``) → our ImageSets files.
SPLIT_FILES = {"train": "train", "training": "train", "val": "val", "validation": "val", "test": "test",
               "testing": "test", "all": None}


def open3d_ml_dataset(dataset_path: str | Path, classes: tuple[str, ...] = ("Chair",)) -> Any:
    """An ``open3d.ml.datasets.KITTI`` over ``dataset_path`` (KITTI layout, ``training/`` + ``ImageSets/``) that
    keeps full scans and the label files' class names; ``classes`` become its ``label_to_names``.

    ``ds.get_split("val").get_data(i)`` gives Open3D-ML's usual dict: ``point`` (N,4) float32 sensor frame,
    ``calib``, ``bounding_boxes`` (``Object3d`` / ``BEVBox3D``, with ``label_class`` from the file).
    """
    try:
        from open3d._ml3d.datasets.kitti import KITTISplit
        from open3d.ml.datasets import KITTI
    except ImportError as e:
        raise InputError(f"Open3D-ML is not available ({e}); install it with: pip install 'open3d-cpu[ml]'") from None
    root = Path(dataset_path)
    if not (root / "training" / "velodyne").is_dir():
        raise InputError("not a KITTI-layout dataset (no training/velodyne/)", root)
    names = dict(enumerate(classes))

    class MpchairSplit(KITTISplit):
        def get_data(self, idx: int) -> dict:
            data = super().get_data(idx)
            data["point"] = data["full_point"]  # no fixed 375 x 1242 crop: our camera is the profile's own
            return data

    class MpchairKITTI(KITTI):
        @staticmethod
        def get_label_to_names() -> dict[int, str]:
            return names

        @staticmethod
        def read_label(path: str, calib: dict) -> list:
            objects = KITTI.read_label(path, calib)
            # KITTI.read_label keeps line order; give each box its file's type back (Object3d maps unknown ones to
            # DontCare), and drop DontCare rows as Open3D-ML's KITTI pipeline would ignore them.
            types = [line.split(" ", 1)[0] for line in Path(path).read_text().splitlines() if line.strip()]
            for obj, name in zip(objects, types):
                obj.label_class = name
            return [o for o in objects if o.label_class != "DontCare"]

        def get_split(self, split: str) -> MpchairSplit:
            return MpchairSplit(self, split=split)

        def get_split_list(self, split: str) -> list[str]:
            if split not in SPLIT_FILES:
                raise ValueError(f"unknown split {split!r} (one of {', '.join(SPLIT_FILES)})")
            velodyne = root / "training" / "velodyne"
            if SPLIT_FILES[split] is None:
                return sorted(str(p) for p in velodyne.glob("*.bin"))
            ids = read_imageset(imageset_path(root, SPLIT_FILES[split]))
            return [str(velodyne / f"{i}.bin") for i in ids]

    return MpchairKITTI(str(root), name="mpchair", use_cache=False)
