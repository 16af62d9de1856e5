#!/usr/bin/python3
"""Reads vispack packed volumes (.vpk) into numpy arrays. Written from format/SPEC.md alone.

Needs numpy and zstandard (Debian: python3-numpy, python3-zstandard); run with /usr/bin/python3.

    from vispack_read import VpkFile
    f = VpkFile("volume.vpk")
    ct = f.read_level("ct", level=0)          # numpy array, shape (z, y, x), int16 HU
    rgba = f.read_level("rgba")               # shape (z, y, x, 4), uint8
    f.verify()                                # raises VpkError naming the first bad brick

Command line:
    vispack_read.py FILE [--channel NAME] [--level L] [--raw OUT.bin] [--verify]
prints a summary; --raw writes the level's voxels as raw little-endian bytes (x fastest);
--verify checks every checksum and the zero padding (pure-Python xxHash64: slow on big files).
Exit codes: 0 ok, 2 usage, 3 I/O, 4 invalid file.
"""
import json
import mmap
import struct
import sys

import numpy as np
import zstandard

MAGIC = b"\x89VPK\r\n\x1a\n"
HEADER = struct.Struct("<8sHHIQQQQQQQQQIIIIIIQQ")
ENTRY = np.dtype([("bx", "<u4"), ("by", "<u4"), ("bz", "<u4"), ("level", "u1"), ("channel", "u1"),
                  ("codec", "u1"), ("reserved", "u1"), ("offset", "<u8"), ("stored_size", "<u8"),
                  ("checksum", "<u8"), ("min", "u1", (8,)), ("max", "u1", (8,)),
                  ("label_first", "<u4"), ("label_count", "<u4")])
TYPES = {"rgba8": (np.dtype("u1"), 4), "int16": (np.dtype("<i2"), 1),
         "uint8": (np.dtype("u1"), 1), "uint16": (np.dtype("<u2"), 1)}
UNIFORM, RAW, ZSTD = 0, 1, 2
ALIGN = 4096
MAX_DIM = 2**31 - 1
MAX_INDEX = 2**26
MAX_META = 64 << 20


class VpkError(Exception):
    """The file is not a valid packed volume (exit code 4)."""


# --- xxHash64 (seed 0), pure Python, from the public algorithm description -----------------
_P1, _P2, _P3, _P4, _P5 = (0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9,
                           0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5)
_M = (1 << 64) - 1


def _rotl(x, r):
    return ((x << r) | (x >> (64 - r))) & _M


def _round(acc, lane):
    return (_rotl((acc + lane * _P2) & _M, 31) * _P1) & _M


def _merge(acc, v):
    return ((acc ^ _round(0, v)) * _P1 + _P4) & _M


def xxh64(data, seed=0):
    data = memoryview(data).cast("B")
    n = len(data)
    i = 0
    if n >= 32:
        v1, v2, v3, v4 = (seed + _P1 + _P2) & _M, (seed + _P2) & _M, seed, (seed - _P1) & _M
        lanes = np.frombuffer(data[: n - n % 32], dtype="<u8").tolist()
        for j in range(0, len(lanes), 4):
            v1 = _round(v1, lanes[j])
            v2 = _round(v2, lanes[j + 1])
            v3 = _round(v3, lanes[j + 2])
            v4 = _round(v4, lanes[j + 3])
        h = (_rotl(v1, 1) + _rotl(v2, 7) + _rotl(v3, 12) + _rotl(v4, 18)) & _M
        for v in (v1, v2, v3, v4):
            h = _merge(h, v)
        i = n - n % 32
    else:
        h = (seed + _P5) & _M
    h = (h + n) & _M
    while i + 8 <= n:
        k = struct.unpack_from("<Q", data, i)[0]
        h = ((_rotl(h ^ _round(0, k), 27) * _P1) + _P4) & _M
        i += 8
    if i + 4 <= n:
        k = struct.unpack_from("<I", data, i)[0]
        h = ((_rotl(h ^ ((k * _P1) & _M), 23) * _P2) + _P3) & _M
        i += 4
    while i < n:
        h = (_rotl(h ^ ((data[i] * _P5) & _M), 11) * _P1) & _M
        i += 1
    h ^= h >> 33
    h = (h * _P2) & _M
    h ^= h >> 29
    h = (h * _P3) & _M
    h ^= h >> 32
    return h


def _align(v, a):
    return (v + a - 1) // a * a


class VpkFile:
    """A packed volume opened read-only with mmap; validated as SPEC.md requires."""

    def __init__(self, path):
        self.path = path
        with open(path, "rb") as fh:
            size = fh.seek(0, 2)
            if size < HEADER.size:
                self._fail(f"truncated or not a vispack file: {size} bytes")
            self._map = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        self.size = size
        (magic, self.major, self.minor, header_size, file_size, payload_offset, payload_end,
         meta_off, meta_size, index_off, index_count, labels_off, labels_count, entry_size,
         self.brick_edge, level_count, channel_count, flags, res0, res1,
         table_checksum) = HEADER.unpack_from(self._map, 0)
        if magic != MAGIC:
            self._fail("not a vispack packed volume (bad magic)")
        if self.major != 1:
            self._fail(f"format version {self.major}.{self.minor} is not supported")
        if file_size != size:
            self._fail(f"truncated or extended: header says {file_size} bytes, file has {size}")
        if (header_size, entry_size, payload_offset, flags, res0, res1) != (128, 64, ALIGN, 0, 0, 0):
            self._fail("bad fixed header field")
        e = self.brick_edge
        if e < 4 or e > 1024 or e & (e - 1):
            self._fail(f"brick_edge {e}")
        if not (payload_end >= ALIGN and payload_end % ALIGN == 0 and payload_end <= size):
            self._fail(f"payload_end {payload_end}")
        if meta_off != payload_end or not 1 <= meta_size <= MAX_META or meta_off + meta_size > size:
            self._fail("metadata block out of range")
        if index_off != _align(meta_off + meta_size, 8) or not 1 <= index_count <= MAX_INDEX:
            self._fail("index block out of range")
        if labels_off != index_off + 64 * index_count or labels_off + 4 * labels_count != size:
            self._fail("index or label IDs do not end at the file end")
        if xxh64(bytes(self._map[0:120]) + bytes(self._map[meta_off:size])) != table_checksum:
            self._fail("table checksum mismatch")
        self.payload_end = payload_end
        self.meta_off, self.meta_size, self.index_off = meta_off, meta_size, index_off
        try:
            self.metadata = json.loads(bytes(self._map[meta_off:meta_off + meta_size]).decode("utf-8"))
        except (ValueError, RecursionError) as err:
            self._fail(f"malformed metadata JSON: {err}")
        m = self.metadata
        try:
            dims = [int(v) for v in m["dims"]]
            self.spacing_mm = [float(v) for v in m["spacing_mm"]]
            self.origin_mm = [float(v) for v in m["origin_mm"]]
            self.channels = [(c["name"], c["type"]) for c in m["channels"]]
            if len(dims) != 3 or any(not 1 <= d <= MAX_DIM for d in dims) or m["brick_edge"] != e:
                raise ValueError("dims or brick_edge")
            if len(self.channels) != channel_count or any(t not in TYPES for _, t in self.channels):
                raise ValueError("channels")
        except (KeyError, TypeError, ValueError) as err:
            self._fail(f"bad metadata: {err}")
        # Levels: halve (rounding up) until the level fits one brick.
        self.levels = []
        d = dims
        while True:
            self.levels.append((tuple(d), tuple(-(-v // e) for v in d)))
            if max(d) <= e:
                break
            d = [-(-v // 2) for v in d]
        if len(self.levels) != level_count:
            self._fail(f"level_count {level_count} disagrees with dims")
        self.level_base = []
        total = 0
        for _, g in self.levels:
            self.level_base.append(total)
            total += g[0] * g[1] * g[2] * channel_count
        if total != index_count:
            self._fail(f"index_count {index_count}, expected {total}")
        self.index = np.frombuffer(self._map, dtype=ENTRY, count=index_count, offset=index_off)
        self.label_ids = np.frombuffer(self._map, dtype="<u4", count=labels_count, offset=labels_off)
        self._check_index()
        self._dctx = zstandard.ZstdDecompressor()

    def _fail(self, what):
        raise VpkError(f"{self.path}: {what}")

    def _name(self, k):
        en = self.index[k]
        return (f"brick level {en['level']} channel {self.channels[en['channel']][0]} "
                f"({en['bx']},{en['by']},{en['bz']})")

    def _check_index(self):
        k = 0
        spans = []
        for level, (_, g) in enumerate(self.levels):
            for c, (_, t) in enumerate(self.channels):
                raw = self.brick_bytes(c)
                for bz in range(g[2]):
                    for by in range(g[1]):
                        for bx in range(g[0]):
                            en = self.index[k]
                            if (en["bx"], en["by"], en["bz"], en["level"], en["channel"]) != (bx, by, bz, level, c):
                                self._fail(f"index entry {k} is out of place")
                            codec, off, n = int(en["codec"]), int(en["offset"]), int(en["stored_size"])
                            if en["reserved"]:
                                self._fail(f"{self._name(k)}: reserved byte")
                            if codec == UNIFORM:
                                if off or n or en["checksum"] or bytes(en["min"]) != bytes(en["max"]):
                                    self._fail(f"{self._name(k)}: bad uniform brick")
                            elif codec in (RAW, ZSTD):
                                if (codec == RAW and n != raw) or (codec == ZSTD and not 1 <= n < raw):
                                    self._fail(f"{self._name(k)}: stored size {n}")
                                if off % ALIGN or off < ALIGN or off + n > self.payload_end:
                                    self._fail(f"{self._name(k)}: payload outside the payload area")
                                spans.append((off, off + n, k))
                            else:
                                self._fail(f"{self._name(k)}: unknown codec {codec}")
                            lf, lc = int(en["label_first"]), int(en["label_count"])
                            if t in ("uint8", "uint16"):
                                if lc == 0 or lf + lc > len(self.label_ids):
                                    self._fail(f"{self._name(k)}: label set out of range")
                            elif lf or lc:
                                self._fail(f"{self._name(k)}: label set on a non-label channel")
                            k += 1
        spans.sort()
        cursor = ALIGN
        for off, end, k in spans:
            if off < cursor:
                self._fail(f"{self._name(k)}: overlapping payload")
            cursor = _align(end, ALIGN)
        if cursor != self.payload_end:
            self._fail("payload_end is not the end of the last payload")
        self._spans = spans

    def channel_index(self, name):
        for i, (n, _) in enumerate(self.channels):
            if n == name:
                return i
        raise KeyError(f"{self.path}: no channel {name!r}")

    def brick_bytes(self, c):
        dt, comps = TYPES[self.channels[c][1]]
        return self.brick_edge ** 3 * dt.itemsize * comps

    def entry(self, c, level, bx, by, bz):
        _, g = self.levels[level]
        k = self.level_base[level] + c * g[0] * g[1] * g[2] + (bz * g[1] + by) * g[0] + bx
        return k, self.index[k]

    def decode_brick(self, c, level, bx, by, bz):
        """One brick as an array of shape (E, E, E[, 4]) indexed [z, y, x]; padding replicated."""
        k, en = self.entry(c, level, bx, by, bz)
        dt, comps = TYPES[self.channels[c][1]]
        e = self.brick_edge
        shape = (e, e, e, comps) if comps > 1 else (e, e, e)
        nbytes = self.brick_bytes(c)
        codec, off, n = int(en["codec"]), int(en["offset"]), int(en["stored_size"])
        if codec == UNIFORM:
            value = np.frombuffer(bytes(en["min"][: dt.itemsize * comps]), dtype=dt)
            return np.broadcast_to(value.reshape((1, 1, 1, comps) if comps > 1 else ()), shape)
        if codec == RAW:
            return np.frombuffer(self._map, dtype=dt, count=nbytes // dt.itemsize, offset=off).reshape(shape)
        try:
            out = self._dctx.decompress(self._map[off:off + n], max_output_size=nbytes)
        except zstandard.ZstdError as err:
            self._fail(f"{self._name(k)}: zstd payload does not decode: {err}")
        if len(out) != nbytes:
            self._fail(f"{self._name(k)}: decodes to {len(out)} bytes, expected {nbytes}")
        return np.frombuffer(out, dtype=dt).reshape(shape)

    def read_level(self, channel, level=0):
        """A whole level of a channel: shape (z, y, x) or (z, y, x, 4)."""
        c = self.channel_index(channel) if isinstance(channel, str) else channel
        (dx, dy, dz), (gx, gy, gz) = self.levels[level]
        dt, comps = TYPES[self.channels[c][1]]
        e = self.brick_edge
        out = np.empty((dz, dy, dx, comps) if comps > 1 else (dz, dy, dx), dtype=dt)
        for bz in range(gz):
            for by in range(gy):
                for bx in range(gx):
                    b = self.decode_brick(c, level, bx, by, bz)
                    z1, y1, x1 = min(dz, (bz + 1) * e), min(dy, (by + 1) * e), min(dx, (bx + 1) * e)
                    out[bz * e:z1, by * e:y1, bx * e:x1] = b[: z1 - bz * e, : y1 - by * e, : x1 - bx * e]
        return out

    def verify(self):
        """Checks every payload checksum and that all padding is zero; raises VpkError."""
        for k, en in enumerate(self.index):
            if int(en["codec"]) != UNIFORM:
                off, n = int(en["offset"]), int(en["stored_size"])
                if xxh64(self._map[off:off + n]) != int(en["checksum"]):
                    self._fail(f"{self._name(k)}: checksum mismatch")
        gaps = [(128, ALIGN)]
        for i, (off, end, k) in enumerate(self._spans):
            nxt = self._spans[i + 1][0] if i + 1 < len(self._spans) else self.payload_end
            gaps.append((end, nxt))
        gaps.append((self.meta_off + self.meta_size, self.index_off))
        for a, b in gaps:
            if any(self._map[a:b]):
                self._fail(f"non-zero padding in [{a}, {b})")


def main(argv):
    import argparse
    p = argparse.ArgumentParser(description="Summarise, verify or dump a vispack packed volume.")
    p.add_argument("file")
    p.add_argument("--channel")
    p.add_argument("--level", type=int, default=0)
    p.add_argument("--raw", help="write the channel's level as raw little-endian voxels (x fastest)")
    p.add_argument("--verify", action="store_true")
    args = p.parse_args(argv)
    try:
        f = VpkFile(args.file)
        print(f"{args.file}: version {f.major}.{f.minor}, dims {f.levels[0][0]}, "
              f"{len(f.levels)} levels, channels {[n for n, _ in f.channels]}")
        if args.verify:
            f.verify()
            print("verify: ok")
        if args.raw:
            if not args.channel:
                p.error("--raw needs --channel")
            if not 0 <= args.level < len(f.levels):
                p.error(f"--level {args.level} is outside [0, {len(f.levels) - 1}]")
            data = f.read_level(args.channel, args.level)
            with open(args.raw, "wb") as out:
                out.write(np.ascontiguousarray(data).tobytes())
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
    sys.exit(main(sys.argv[1:]))
