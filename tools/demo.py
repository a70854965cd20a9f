"""``make demo``: synthesize one house, generate a 200-frame Matterport-Chair dataset from it, print where it is.

Writes ``out/demo/houses/`` (the synthetic house in the Matterport3D release format) and ``out/demo/dataset/`` (KITTI
layout + manifest). Re-running resumes / reuses what is there (same seed, same bytes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _house_is_there(houses: Path, house) -> bool:
    """Whether ``houses`` already holds ``house``'s release-layout files, byte for byte."""
    folder = houses / "v1" / "scans" / house.id / "house_segmentations"
    files = {folder / f"{house.id}{suffix}": data for suffix, data in house.files().items()}
    return all(path.is_file() and path.read_bytes() == data for path, data in files.items())


def main(argv: list[str] | None = None) -> int:
    from mpchair.core.errors import InputError
    from mpchair.dataset.generate import GenerateRequest, default_workers, generate
    from mpchair.synth import synthesize_house, write_house

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "demo", help="demo folder (default out/demo)")
    p.add_argument("--frames", type=int, default=200, help="frames to generate (default 200)")
    p.add_argument("--seed", type=int, default=0, help="seed of the house and of the dataset")
    p.add_argument("--workers", type=int, default=min(2, default_workers()), help="worker processes")
    args = p.parse_args(argv)
    try:
        houses = args.out / "houses"
        house = synthesize_house(args.seed)
        chairs = sum(o.mpcat40_name == "chair" for o in house.objects)
        if _house_is_there(houses, house):  # a re-run: same seed, same bytes, nothing to write
            print(f"house {house.id} already in {houses} (nothing synthesized)", file=sys.stderr)
        else:
            write_house(houses, house)
            print(f"synthesized house {house.id}: {len(house.faces)} faces, {chairs} chairs -> {houses}",
                  file=sys.stderr)
        summary = generate(GenerateRequest(root=houses, houses=(house.id,), frames=args.frames,
                                           out=args.out / "dataset", seed=args.seed, workers=args.workers))
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary.out)
    print(summary.line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
