"""Parsing and validation of a .vpk file's header, metadata and brick index (format/SPEC.md).

Everything here runs once when a file is opened, before any offset or size is used: a hostile or
damaged file raises VpkError naming what is wrong (and, for index entries, the level, channel and
brick), never a crash. The checks over the index are vectorised with numpy, so opening a file with
millions of bricks stays fast.
"""
import json
import math
import struct
from dataclasses import dataclass

import numpy as np

from .checksum import xxh64

MAGIC = b"\x89VPK\r\n\x1a\n"
HEADER = struct.Struct("<8sHHIQQQQQQQQQIIIIIIQQ")
HEADER_SIZE = 128
ENTRY = np.dtype([("bx", "<u4"), ("by", "<u4"), ("bz", "<u4"), ("level", "u1"), ("channel", "u1"),
                  ("codec", "u1"), ("reserved", "u1"), ("offset", "<u8"), ("stored_size", "<u8"),
                  ("checksum", "<u8"), ("min", "u1", (8,)), ("max", "u1", (8,)),
                  ("label_first", "<u4"), ("label_count", "<u4")])
# Channel type -> (numpy dtype of one component, components per voxel).
TYPES = {"rgba8": (np.dtype("u1"), 4), "int16": (np.dtype("<i2"), 1),
         "uint8": (np.dtype("u1"), 1), "uint16": (np.dtype("<u2"), 1)}
LABEL_TYPES = ("uint8", "uint16")
UNIFORM, RAW, ZSTD = 0, 1, 2
CODEC_NAMES = {UNIFORM: "uniform", RAW: "raw", ZSTD: "zstd"}
ALIGN = 4096
MAX_DIM = 2**31 - 1
MAX_META = 64 << 20
MAX_INDEX = 2**26
MAX_LABELS = 2**28
MAX_LEVEL_VOXELS = 2**48
MAX_JSON_DEPTH = 64


class VpkError(Exception):
    """The file is not a valid packed volume (the command line exits with code 4)."""


@dataclass(frozen=True)
class Header:
    """The 128-byte FileHeader; offsets and sizes in bytes from the start of the file."""
    major: int
    minor: int
    file_size: int
    payload_end: int
    meta_off: int
    meta_size: int
    index_off: int
    index_count: int
    labels_off: int
    labels_count: int
    brick_edge: int
    level_count: int
    channel_count: int
    table_checksum: int


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of the metadata: name, type name, component dtype, components per voxel."""
    name: str
    type: str
    dtype: np.dtype
    components: int

    @property
    def brick_bytes_per_voxel(self):
        """Bytes of one voxel (all components)."""
        return self.dtype.itemsize * self.components


@dataclass(frozen=True)
class LevelInfo:
    """Geometry of one pyramid level; tuples in (x, y, z) order as SPEC.md writes them."""
    dims: tuple          # voxels along x, y, z
    grid: tuple          # bricks along x, y, z
    spacing_mm: tuple    # voxel spacing along x, y, z in mm
    origin_mm: tuple     # centre of voxel (0, 0, 0) in mm
    index_base: int      # index entry of brick (0, 0, 0) of channel 0

    @property
    def brick_count(self):
        """Bricks of one channel at this level."""
        return self.grid[0] * self.grid[1] * self.grid[2]


def _align(v, a):
    return (v + a - 1) // a * a


def fail(path, what):
    """Raises VpkError with the file path in front of the message."""
    raise VpkError(f"{path}: {what}")


def parse_header(buf, size, path):
    """Reads and checks the header against the real file size; returns a Header."""
    if size < HEADER_SIZE:
        fail(path, f"truncated or not a vispack file: {size} bytes")
    (magic, major, minor, header_size, file_size, payload_offset, payload_end, meta_off, meta_size,
     index_off, index_count, labels_off, labels_count, entry_size, brick_edge, level_count,
     channel_count, flags, res0, res1, table_checksum) = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        fail(path, "not a vispack packed volume (bad magic)")
    if major != 1:
        fail(path, f"format version {major}.{minor} is not supported (this reader reads 1.x)")
    if file_size != size:
        fail(path, f"truncated or extended: header says {file_size} bytes, file has {size}")
    if (header_size, entry_size, payload_offset, flags, res0, res1) != (128, 64, ALIGN, 0, 0, 0):
        fail(path, "bad fixed header field (header_size, entry size, payload offset or reserved)")
    e = brick_edge
    if e < 4 or e > 1024 or e & (e - 1):
        fail(path, f"brick_edge {e} is not a power of two in [4, 1024]")
    if not (1 <= level_count <= 64 and 1 <= channel_count <= 255):
        fail(path, f"level_count {level_count} or channel_count {channel_count} out of range")
    if not (payload_end >= ALIGN and payload_end % ALIGN == 0 and payload_end <= size):
        fail(path, f"payload_end {payload_end} outside the file")
    if meta_off != payload_end or not 1 <= meta_size <= MAX_META or meta_off + meta_size > size:
        fail(path, f"metadata block [{meta_off}, +{meta_size}) out of range")
    if index_off != _align(meta_off + meta_size, 8) or not 1 <= index_count <= MAX_INDEX:
        fail(path, f"index block at {index_off} with {index_count} entries out of range")
    if labels_count > MAX_LABELS or labels_off != index_off + 64 * index_count or \
            labels_off + 4 * labels_count != size:
        fail(path, "index or label IDs do not end at the file end")
    return Header(major, minor, file_size, payload_end, meta_off, meta_size, index_off, index_count,
                  labels_off, labels_count, brick_edge, level_count, channel_count, table_checksum)


def check_table_checksum(buf, h, path):
    """SPEC 'Checksums': xxh64(header[0:120] || metadata .. end of file) == table_checksum."""
    if xxh64(bytes(buf[0:120]) + bytes(buf[h.meta_off:h.file_size])) != h.table_checksum:
        fail(path, "table checksum mismatch (header, metadata, index or label IDs changed)")


def _json_depth(value):
    """Nesting depth of a parsed JSON value (iterative: no recursion limit)."""
    depth, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, (dict, list)):
            depth = max(depth, d)
            stack.extend((c, d + 1) for c in (v.values() if isinstance(v, dict) else v))
    return depth


def parse_metadata(buf, h, path):
    """The metadata JSON object, parsed and checked for nesting depth."""
    try:
        meta = json.loads(bytes(buf[h.meta_off:h.meta_off + h.meta_size]).decode("utf-8"))
    except (ValueError, RecursionError) as err:
        fail(path, f"malformed metadata JSON: {err}")
    if not isinstance(meta, dict):
        fail(path, "metadata is not a JSON object")
    if _json_depth(meta) > MAX_JSON_DEPTH:
        fail(path, f"metadata nests deeper than {MAX_JSON_DEPTH}")
    return meta


def _vec3(value, what, positive=False):
    v = [float(x) for x in value]
    if len(v) != 3 or not all(math.isfinite(x) and (x > 0 or not positive) for x in v):
        raise ValueError(f"{what} {value}")
    return tuple(v)


def parse_channels(meta, h):
    """ChannelInfo per channel, checked against the header's channel_count."""
    channels = []
    for c in meta["channels"]:
        name, type_ = c["name"], c["type"]
        if not isinstance(name, str) or not name or type_ not in TYPES:
            raise ValueError(f"channel {name!r} of type {type_!r}")
        dtype, comps = TYPES[type_]
        if int(c.get("components", comps)) != comps:
            raise ValueError(f"channel {name!r}: components {c['components']}")
        channels.append(ChannelInfo(name, type_, dtype, comps))
    if len(channels) != h.channel_count or len({c.name for c in channels}) != len(channels):
        raise ValueError(f"{len(channels)} channels (header: {h.channel_count}) or a repeated name")
    return tuple(channels)


def level_geometry(dims, spacing, origin, h):
    """LevelInfo per level: halve (rounding up) until the level fits one brick (SPEC 'Levels')."""
    e, levels, base, d = h.brick_edge, [], 0, list(dims)
    while True:
        if d[0] * d[1] * d[2] > MAX_LEVEL_VOXELS:
            raise ValueError(f"level of {d} voxels is over the limit")
        grid = tuple(-(-v // e) for v in d)
        scale = 2 ** len(levels)
        levels.append(LevelInfo(tuple(d), grid, tuple(s * scale for s in spacing),
                                tuple(o + (scale - 1) / 2 * s for o, s in zip(origin, spacing)),
                                base))
        base += grid[0] * grid[1] * grid[2] * h.channel_count
        if max(d) <= e or len(levels) > 64:
            return tuple(levels), base
        d = [-(-v // 2) for v in d]


def parse_geometry(meta, h, path):
    """(channels, levels) from the metadata, checked against the header."""
    try:
        if meta.get("format") != "vispack":
            raise ValueError(f"format {meta.get('format')!r}")
        dims = [int(v) for v in meta["dims"]]
        if len(dims) != 3 or any(not 1 <= d <= MAX_DIM for d in dims):
            raise ValueError(f"dims {meta['dims']}")
        if meta["brick_edge"] != h.brick_edge:
            raise ValueError(f"brick_edge {meta['brick_edge']} (header: {h.brick_edge})")
        spacing = _vec3(meta["spacing_mm"], "spacing_mm", positive=True)
        origin = _vec3(meta["origin_mm"], "origin_mm")
        channels = parse_channels(meta, h)
        levels, total = level_geometry(dims, spacing, origin, h)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
        fail(path, f"bad metadata: {err}")
    if len(levels) != h.level_count:
        fail(path, f"level_count {h.level_count} disagrees with dims (expected {len(levels)})")
    if total != h.index_count:
        fail(path, f"index_count {h.index_count}, dims give {total}")
    return channels, levels


def brick_name(index, k, channels):
    """'level L channel NAME brick (bx,by,bz)' for index entry k."""
    en = index[k]
    c = int(en["channel"])
    name = channels[c].name if c < len(channels) else f"#{c}"
    return f"level {en['level']} channel {name} brick ({en['bx']},{en['by']},{en['bz']})"


def _expected_positions(levels, nchan):
    """(bx, by, bz, level, channel) arrays every index entry must hold, in index order."""
    parts = []
    for lv, info in enumerate(levels):
        gx, gy, _ = info.grid
        k = np.arange(info.brick_count, dtype=np.int64)
        one = np.stack([k % gx, (k // gx) % gy, k // (gx * gy)], axis=1)
        column = np.ones((len(k), 1), np.int64)
        for c in range(nchan):
            parts.append(np.concatenate([one, column * lv, column * c], axis=1))
    return np.concatenate(parts)


def _first_failure(checks):
    """checks: (boolean mask over entries, message) pairs; returns (k, message) of the first bad
    entry (lowest k, then the first check), or None."""
    best = None
    for mask, message in checks:
        bad = np.flatnonzero(mask)
        if len(bad) and (best is None or bad[0] < best[0]):
            best = (int(bad[0]), message)
    return best


def _entry_checks(index, channels, levels, h):
    """The per-entry rules of SPEC 'Brick index' as (mask, message) pairs."""
    codec = index["codec"]
    off, n = index["offset"], index["stored_size"]
    chan = np.minimum(index["channel"].astype(np.int64), len(channels) - 1)  # positions checked
    voxel_bytes = np.array([c.brick_bytes_per_voxel for c in channels], np.uint64)
    raw = voxel_bytes[chan] * np.uint64(h.brick_edge ** 3)
    is_label = np.array([c.type in LABEL_TYPES for c in channels])[chan]
    uniform, payload = codec == UNIFORM, (codec == RAW) | (codec == ZSTD)
    pend = np.uint64(h.payload_end)
    lf, lc = index["label_first"].astype(np.uint64), index["label_count"].astype(np.uint64)
    return [
        (index["reserved"] != 0, "reserved byte is not zero"),
        (~uniform & ~payload, "unknown codec"),
        (uniform & ((off != 0) | (n != 0) | (index["checksum"] != 0)
                    | np.any(index["min"] != index["max"], axis=1)), "bad uniform brick"),
        ((codec == RAW) & (n != raw), "raw payload size is not the brick size"),
        ((codec == ZSTD) & ((n < 1) | (n >= raw)), "zstd payload size out of range"),
        (payload & ((off % np.uint64(ALIGN) != 0) | (off < np.uint64(ALIGN)) | (off > pend)
                    | (n > pend - np.minimum(off, pend))),
         f"payload outside the payload area [4096, {h.payload_end})"),
        (is_label & ((lc == 0) | (lf + lc > np.uint64(h.labels_count))), "label set out of range"),
        (~is_label & ((lf != 0) | (lc != 0)), "label set on a non-label channel"),
    ]


def _check_no_overlap(index, channels, h, path):
    """Payloads sorted by offset must not overlap and must end at payload_end (rounded to 4096)."""
    payload = np.flatnonzero(index["codec"] != UNIFORM)
    off = index["offset"][payload].astype(np.int64)
    order = np.argsort(off, kind="stable")
    ks, off = payload[order], off[order]
    end = off + index["stored_size"][ks].astype(np.int64)
    cursor = np.concatenate([[ALIGN], (end + ALIGN - 1) // ALIGN * ALIGN])
    bad = np.flatnonzero(off < cursor[:-1])
    if len(bad):
        fail(path, f"{brick_name(index, int(ks[bad[0]]), channels)}: overlapping payload")
    if int(cursor[-1]) != h.payload_end:
        fail(path, f"payload_end {h.payload_end} is not the end of the last payload ({cursor[-1]})")
    return list(zip(off.tolist(), end.tolist()))


def check_index(index, label_ids, channels, levels, h, path):
    """Validates every index entry (vectorised); returns the sorted payload spans (start, end)."""
    expected = _expected_positions(levels, len(channels))
    got = np.stack([index[f].astype(np.int64) for f in ("bx", "by", "bz", "level", "channel")], 1)
    misplaced = np.flatnonzero(np.any(got != expected, axis=1))
    if len(misplaced):
        k = int(misplaced[0])
        lv, c = int(expected[k, 3]), int(expected[k, 4])
        fail(path, f"index entry {k} (level {lv} channel {channels[c].name} brick "
                   f"({expected[k, 0]},{expected[k, 1]},{expected[k, 2]})) is out of place")
    first = _first_failure(_entry_checks(index, channels, levels, h))
    if first:
        k, message = first
        fail(path, f"{brick_name(index, k, channels)}: {message}")
    return _check_no_overlap(index, channels, h, path)
