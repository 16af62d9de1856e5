"""vispack: read packed, bricked volumes (.vpk, format/SPEC.md) lazily from a memory map.

    import vispack
    f = vispack.open("volume.vpk")            # validated at open (header, table checksum, index)
    f.channel_names                           # e.g. ['rgba', 'ct', 'labels']
    ct1 = f["ct"].level(1)                    # lazy array, shape (z, y, x), int16 HU
    roi = ct1[10:20, 32:96, 0:64]             # numpy array; decodes only the bricks it covers

    import dask.array as da
    d = da.from_array(f["ct"].level(0), chunks=f["ct"].level(0).chunks)

Arrays are indexed [z, y, x] (x = image column, y = image row, z = slice; x fastest in the file);
rgba8 channels add a last axis of 4 components (r, g, b, alpha). Geometry tuples (spacing_mm,
origin_mm) are (x, y, z) in mm. Needs numpy and zstandard (Debian python3-numpy,
python3-zstandard); python3-xxhash makes checksum verification fast; python3-dask for dask.
Errors in the file raise VpkError naming the file and, for bricks, level, channel and brick.
"""
from .checksum import have_fast_xxh64, xxh64
from .layout import VpkError
from .volume import Channel, Level, VpkFile, open

__all__ = ["open", "VpkFile", "Channel", "Level", "VpkError", "xxh64", "have_fast_xxh64"]
