"""The realism calibration of docs/matterport.md: synthetic houses of each realism preset, scanned at the original
code's settings, measured against the original Matterport-Chair dataset (``mpchair.analysis.calibration``).

    .venv/bin/python tools/realism_calibration.py --seeds 0,1,2,3,4,5 --houses 8 --frames 40   # the doc's table
    .venv/bin/python tools/realism_calibration.py --height 1.0 --work out/cal-1m ...   # the paper's sensor height

Writes WORK/calibration.json, the table between the ``calibration-table`` markers of docs/matterport.md (--doc; at
another --height than the original's 1.25 m, the ``calibration-table-<height>m`` markers: --marker), and, at 1.25 m,
the pictures docs/img/realism-house.png and docs/img/realism-hole-frame.png (--pictures). Houses and finished datasets
in WORK are reused (generate resumes), so a second run only re-measures: after changing the synthesizer, use a new
--work.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mpchair.analysis.calibration import (
    MARKER,
    ORIGINAL_HEIGHT,
    CalibrationPlan,
    calibrate,
    dataset_of,
    format_table,
    hole_picture,
    write_doc_table,
)
from mpchair.analysis.render import house_picture
from mpchair.core.atomic import write_text
from mpchair.matterport import find_houses

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "realism-calibration", help="houses and datasets")
    ap.add_argument("--seeds", default="1,2,3,4", help="synth seeds, comma-separated")
    ap.add_argument("--houses", type=int, default=2, help="houses per seed")
    ap.add_argument("--frames", type=int, default=150, help="frames per house")
    ap.add_argument("--height", type=float, default=1.25, help="sensor height above the floor (m)")
    ap.add_argument("--robot-radius", type=float, default=0.1, help="robot radius (m)")
    ap.add_argument("--presets", default="clean,default", help="realism presets, comma-separated")
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "matterport.md", help="doc whose table to rewrite")
    ap.add_argument("--marker", help="name of the doc's markers to write between (default: calibration-table at "
                    "1.25 m, else calibration-table-<height>m)")
    ap.add_argument("--no-doc", action="store_true", help="print the table, leave the doc alone")
    ap.add_argument("--pictures", type=Path, default=ROOT / "docs" / "img", help="where the two PNGs go")
    ap.add_argument("--no-pictures", action="store_true", help="no pictures (never drawn at another height)")
    args = ap.parse_args(argv)
    plan = CalibrationPlan(work=args.work, presets=tuple(args.presets.split(",")),
                           seeds=tuple(int(s) for s in args.seeds.split(",")), houses=args.houses, frames=args.frames,
                           height=args.height, robot_radius=args.robot_radius)
    rows = calibrate(plan, progress=True)
    record = {"plan": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}, "rows": rows}
    write_text(plan.work / "calibration.json", json.dumps(record, indent=1) + "\n")
    table = format_table(rows, plan)
    if args.no_doc:
        print(table)
    else:
        marker = args.marker or (MARKER if plan.height == ORIGINAL_HEIGHT else f"{MARKER}-{plan.height:g}m")
        write_doc_table(args.doc, table, marker)
        print(f"wrote the table into {args.doc} ({marker})")
    if not args.no_pictures and "default" in plan.presets and plan.height == ORIGINAL_HEIGHT:
        data = dataset_of(plan, "default", plan.seeds[0])
        houses = data.parent / "houses"
        hid = sorted(find_houses(houses))[0]
        print(house_picture(houses, hid, args.pictures / "realism-house.png", dataset=data)["out"])
        print(hole_picture(data, houses, args.pictures / "realism-hole-frame.png")["out"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
