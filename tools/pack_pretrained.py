"""Pack a training's ``last.pt`` as packaged weights for ``--checkpoint pretrained:NAME`` (half precision, model and
config only, listed in ``detector/pretrained/index.json``): ``detector.checkpoint.pack_pretrained``.

    .venv/bin/python tools/pack_pretrained.py RUN/last.pt --name sparse=mpchair_sparse_cpu \\
        --name sparse_exact=mpchair_sparse_exact_cpu [--dtype bf16] [--out detector/pretrained]
"""

import argparse
import sys

from detector.checkpoint import PACK_DTYPES, pack_pretrained
from detector.pretrained import PRETRAINED_DIR
from mpchair.core.errors import InputError


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("checkpoint", help="a detector train run's last.pt (or checkpoints/epoch_NNN.pt)")
    p.add_argument("--name", action="append", required=True, metavar="NAME=CONFIG",
                   help="a name for the weights and the packaged config to use them with; repeat (the first names "
                        "the file)")
    p.add_argument("--dtype", choices=sorted(PACK_DTYPES), default="bf16", help="stored precision (default bf16)")
    p.add_argument("--out", default=str(PRETRAINED_DIR), help=f"folder of the weights and index.json (default "
                                                              f"{PRETRAINED_DIR})")
    args = p.parse_args()
    try:
        if any("=" not in n for n in args.name):
            raise InputError("--name takes NAME=CONFIG (e.g. sparse=mpchair_sparse_cpu)")
        names = dict(n.split("=", 1) for n in args.name)
        out = pack_pretrained(args.checkpoint, names, args.out, dtype=args.dtype)
    except (InputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB) and {out.parent / 'index.json'}: "
          + ", ".join(f"pretrained:{n}" for n in names))
    return 0


raise SystemExit(main())
