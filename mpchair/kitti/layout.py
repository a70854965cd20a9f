"""The KITTI folder layout: where one frame's files live, and an image's size read from its PNG header."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from mpchair.core.errors import InputError


@dataclasses.dataclass(frozen=True)
class FramePaths:
    """The four files of one frame under ``<root>/<split_dir>/``."""

    velodyne: Path
    label_2: Path
    calib: Path
    image_2: Path


def frame_paths(root: str | Path, frame_id: str | int, split_dir: str = "training") -> FramePaths:
    """Paths of frame ``frame_id`` (``"000123"`` or ``123``) in the KITTI layout ``<root>/<split_dir>/<kind>/``."""
    fid = f"{frame_id:06d}" if isinstance(frame_id, int) else str(frame_id)
    base = Path(root) / split_dir
    return FramePaths(
        velodyne=base / "velodyne" / f"{fid}.bin",
        label_2=base / "label_2" / f"{fid}.txt",
        calib=base / "calib" / f"{fid}.txt",
        image_2=base / "image_2" / f"{fid}.png",
    )


def imageset_path(root: str | Path, split: str) -> Path:
    """``<root>/ImageSets/<split>.txt``."""
    return Path(root) / "ImageSets" / f"{split}.txt"


def read_image_size(path: str | Path) -> tuple[int, int]:
    """Image ``(W, H)`` in pixels of a PNG (KITTI's image_2 format), from the file header only (no pixel decoding)."""
    path = Path(path)
    try:
        # Pillow parses the header lazily (pixels are decoded only on load()); naming the format skips probing every
        # other plugin, which is most of the cost for a file that is not a PNG.
        with Image.open(path, formats=("PNG",)) as im:
            return int(im.width), int(im.height)
    except FileNotFoundError:
        raise InputError("image file not found", path) from None
    except (UnidentifiedImageError, OSError) as e:
        raise InputError(f"cannot read image header: {e}", path) from None
