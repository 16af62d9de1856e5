"""Command line: summarise, verify or dump a packed volume (scripts/vispack_read.py calls main).

    vispack_read.py FILE [--channel NAME] [--level L] [--region Z0:Z1,Y0:Y1,X0:X1] [--raw OUT.bin]
                    [--verify]

--raw writes the channel's level (or the --region of it) as raw little-endian voxels, x fastest;
--verify checks every checksum and the zero padding. Exit codes: 0 ok, 2 usage, 3 I/O,
4 invalid file.
"""
import argparse
import sys

import numpy as np

from .layout import VpkError
from .volume import VpkFile


def _parse_region(text):
    """'z0:z1,y0:y1,x0:x1' (numpy slice syntax per axis, [z, y, x]) -> tuple of slices/ints."""
    key = []
    for part in text.split(","):
        if ":" in part:
            bits = [int(b) if b.strip() else None for b in part.split(":")]
            key.append(slice(*bits))
        else:
            key.append(int(part))
    return tuple(key)


def _parser():
    p = argparse.ArgumentParser(prog="vispack_read.py",
                                description="Summarise, verify or dump a vispack packed volume.")
    p.add_argument("file")
    p.add_argument("--channel")
    p.add_argument("--level", type=int, default=0)
    p.add_argument("--region", help="z0:z1,y0:y1,x0:x1 (indices [z, y, x], numpy slices)")
    p.add_argument("--raw", help="write the level (or region) as raw little-endian voxels, "
                                 "x fastest")
    p.add_argument("--verify", action="store_true", help="check every checksum and the padding")
    return p


def _dump(p, f, args):
    """Writes the selected voxels to args.raw."""
    if not args.channel:
        p.error("--raw needs --channel")
    if not 0 <= args.level < f.level_count:
        p.error(f"--level {args.level} is outside [0, {f.level_count - 1}]")
    level = f[args.channel].level(args.level)
    try:
        key = _parse_region(args.region) if args.region else (...,)
    except ValueError:
        p.error(f"--region {args.region!r}: expected z0:z1,y0:y1,x0:x1")
    try:
        data = level[key]
    except (IndexError, TypeError) as err:
        p.error(f"--region {args.region!r}: {err}")
    data = np.ascontiguousarray(data)
    with open(args.raw, "wb") as out:
        out.write(data.tobytes())
    print(f"wrote {args.raw} ({args.channel}, level {args.level}, shape [z, y, x] "
          f"{list(data.shape[:3])}, {data.dtype.str})")


def main(argv=None):
    """Runs the command line; returns the exit code."""
    p = _parser()
    args = p.parse_args(argv)
    try:
        with VpkFile(args.file) as f:
            print(f"{args.file}: version {f.major}.{f.minor}, dims {f.levels[0].dims}, "
                  f"{f.level_count} levels, channels {f.channel_names}")
            if args.verify:
                f.verify()
                print("verify: ok")
            if args.raw:
                _dump(p, f, args)
    except VpkError as err:
        print(f"vispack_read.py: error: {err}", file=sys.stderr)
        return 4
    except KeyError as err:
        print(f"vispack_read.py: error: {err.args[0]}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"vispack_read.py: error: {err}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
