#!/usr/bin/python3
"""Reads vispack packed volumes (.vpk): a thin command line over the `vispack` package in
python/vispack/ (written from format/SPEC.md alone). Run with /usr/bin/python3 (Debian's numpy and
zstandard: python3-numpy, python3-zstandard; python3-xxhash makes --verify fast).

    vispack_read.py FILE [--channel NAME] [--level L] [--region Z0:Z1,Y0:Y1,X0:X1] [--raw OUT.bin]
                    [--verify]

prints a summary; --raw writes the level (or region, indices [z, y, x]) as raw little-endian
voxels, x fastest; --verify checks every checksum and the zero padding.
Exit codes: 0 ok, 2 usage, 3 I/O, 4 invalid file.

As a module (the old API, kept): `from vispack_read import VpkFile` with read_level(channel, level)
and verify(); new code should `import vispack` (add python/ to sys.path or PYTHONPATH).
"""
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))

from vispack import VpkError, VpkFile, xxh64  # noqa: E402  (re-exported: the old module API)
from vispack.cli import main  # noqa: E402

__all__ = ["VpkError", "VpkFile", "xxh64", "main"]

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
