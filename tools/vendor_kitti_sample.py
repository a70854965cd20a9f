"""Build ``tests/data/kitti/`` from the 6-frame KITTI sample: labels and calibs copied byte for byte, scans cropped to
the image_2 field of view, and placeholder (black, 1-bit) PNGs of each frame's real image size.

Usage: ``python tools/vendor_kitti_sample.py [--src /work/shared/kitti_sample] [--dst tests/data/kitti]``.
Re-running it gives byte-identical files.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

from PIL import Image

from mpchair.core.atomic import write_bytes
from mpchair.geometry import fov_mask
from mpchair.kitti import (
    frame_paths,
    read_calib,
    read_image_size,
    read_imageset,
    read_labels,
    read_velodyne,
    write_imageset,
    write_velodyne,
)


def vendor(src: Path, dst: Path) -> list[tuple[str, int, int, tuple[int, int]]]:
    """Write the reduced copy of every frame listed in ``src/ImageSets/train.txt``; returns per-frame sizes."""
    ids = read_imageset(src / "ImageSets" / "train.txt")
    report = []
    for fid in ids:
        s, d = frame_paths(src, fid), frame_paths(dst, fid)
        read_labels(s.label_2)  # validate before copying
        calib = read_calib(s.calib)
        write_bytes(d.label_2, s.label_2.read_bytes())
        write_bytes(d.calib, s.calib.read_bytes())
        size = read_image_size(s.image_2)
        points = read_velodyne(s.velodyne)
        keep = fov_mask(points, calib, size)
        write_velodyne(d.velodyne, points[keep])
        buf = io.BytesIO()
        Image.new("1", size, 0).save(buf, format="PNG", optimize=True)  # placeholder pixels, real size
        write_bytes(d.image_2, buf.getvalue())
        report.append((fid, len(points), int(keep.sum()), size))
    for split in ("train", "val"):
        write_imageset(dst / "ImageSets" / f"{split}.txt", ids)
    return report


def main() -> None:
    repo = Path(__file__).resolve().parent.parent
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=Path("/work/shared/kitti_sample"))
    ap.add_argument("--dst", type=Path, default=repo / "tests" / "data" / "kitti")
    args = ap.parse_args()
    for fid, n_all, n_kept, (w, h) in vendor(args.src, args.dst):
        print(f"{fid}: {n_all} -> {n_kept} points in the image_2 FOV, image {w}x{h}")


if __name__ == "__main__":
    main()
