"""Lazy, memory-mapped access to a .vpk packed volume.

    f = vispack.open("volume.vpk")
    ct = f["ct"].level(1)                    # a Level: shape (z, y, x), dtype int16 (HU)
    block = ct[10:40, 0:64:2, -32:]          # numpy array; only the bricks it covers are decoded
    rgba = f["rgba"].level(0)[5]             # one slice, shape (y, x, 4), uint8

Arrays are indexed [z, y, x] (x fastest in memory, as in the file); an rgba8 channel adds a last
axis of 4 components (r, g, b, alpha). Spacing and origin tuples are in (x, y, z) order, in mm, as
SPEC.md writes them. Nothing is cached: each region read decodes the bricks it covers once.
"""
import builtins
import mmap
import os

import numpy as np
import zstandard

from . import layout
from .checksum import xxh64
from .layout import ALIGN, RAW, UNIFORM


def open(path, verify_checksums=False, on_decode=None):  # noqa: A001 (vispack.open, like io.open)
    """Opens a packed volume read-only (memory-mapped); see VpkFile."""
    return VpkFile(path, verify_checksums=verify_checksums, on_decode=on_decode)


class VpkFile:
    """A packed volume opened read-only with mmap, validated as SPEC.md requires.

    verify_checksums: check each brick payload's xxh64 when it is read (fast with python3-xxhash,
    pure Python otherwise). on_decode: optional callable(level, channel_name, bx, by, bz, codec)
    called once per brick a read touches (instrumentation: tests count decoded bricks with it).
    The table checksum (header, metadata, index, label IDs) is always checked at open.
    """

    def __init__(self, path, verify_checksums=False, on_decode=None):
        self.path = os.fspath(path)
        self.verify_checksums = verify_checksums
        self.on_decode = on_decode
        self._map = None
        with builtins.open(self.path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size < layout.HEADER_SIZE:
                layout.fail(self.path, f"truncated or not a vispack file: {size} bytes")
            self._map = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        self._identity = (self.path, size, os.stat(self.path).st_mtime_ns)
        h = layout.parse_header(self._map, size, self.path)
        layout.check_table_checksum(self._map, h, self.path)
        self.header = h
        self.metadata = layout.parse_metadata(self._map, h, self.path)
        self.channel_infos, self.levels = layout.parse_geometry(self.metadata, h, self.path)
        # Copies (small): the file can be closed while they live.
        self.index = np.frombuffer(self._map, layout.ENTRY, h.index_count, h.index_off).copy()
        self.label_ids = np.frombuffer(self._map, "<u4", h.labels_count, h.labels_off).copy()
        self._spans = layout.check_index(self.index, self.label_ids, self.channel_infos,
                                         self.levels, h, self.path)

    # --- pickling (dask.distributed ships the array's source to workers): reopen by path ---
    def __getstate__(self):
        return {"path": self.path, "verify_checksums": self.verify_checksums,
                "on_decode": self.on_decode}

    def __setstate__(self, state):
        self.__init__(state["path"], state["verify_checksums"], state["on_decode"])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        """Unmaps the file; Level objects of it can no longer read. Arrays still viewing the map
        (raw bricks from brick_view) keep it mapped until they are freed."""
        if self._map is not None:
            try:
                self._map.close()
            except BufferError:  # views exist: the map goes when the last one is freed
                pass
            self._map = None

    def __repr__(self):
        d = self.levels[0].dims
        return (f"<vispack file {self.path!r}: {d[0]}x{d[1]}x{d[2]} voxels (x, y, z), "
                f"{len(self.levels)} levels, channels {self.channel_names}>")

    @property
    def major(self):
        """Format major version."""
        return self.header.major

    @property
    def minor(self):
        """Format minor version."""
        return self.header.minor

    @property
    def brick_edge(self):
        """Voxels along each edge of a brick."""
        return self.header.brick_edge

    @property
    def level_count(self):
        """Number of pyramid levels (level 0 is full resolution)."""
        return len(self.levels)

    @property
    def channel_names(self):
        """Channel names in file order."""
        return [c.name for c in self.channel_infos]

    @property
    def spacing_mm(self):
        """Level-0 voxel spacing (x, y, z) in mm."""
        return self.levels[0].spacing_mm

    @property
    def origin_mm(self):
        """Centre of level-0 voxel (0, 0, 0), (x, y, z) in mm."""
        return self.levels[0].origin_mm

    def channel_index(self, name):
        """Index of the channel called name; KeyError naming the file's channels otherwise."""
        for i, c in enumerate(self.channel_infos):
            if c.name == name:
                return i
        raise KeyError(f"{self.path}: no channel {name!r} (the file has {self.channel_names})")

    def __getitem__(self, name):
        """The Channel called name (or of that index)."""
        c = name if isinstance(name, int) else self.channel_index(name)
        if not 0 <= c < len(self.channel_infos):
            raise KeyError(f"{self.path}: no channel #{c}")
        return Channel(self, c)

    def __iter__(self):
        return iter(self.channel_names)

    def __len__(self):
        return len(self.channel_infos)

    def __contains__(self, name):
        return name in self.channel_names

    # --- bricks ----------------------------------------------------------------------------
    def entry_number(self, c, level, bx, by, bz):
        """Index entry number of brick (bx, by, bz) of channel c at a level (SPEC arithmetic)."""
        info = self.levels[level]
        gx, gy, _ = info.grid
        return info.index_base + c * info.brick_count + (bz * gy + by) * gx + bx

    def _brick_name(self, k):
        return layout.brick_name(self.index, k, self.channel_infos)

    def _payload(self, k, nbytes):
        """The payload bytes of entry k (a memoryview into the map), bounds re-checked."""
        if self._map is None:
            raise ValueError(f"{self.path}: file is closed")
        en = self.index[k]
        off, n = int(en["offset"]), int(en["stored_size"])
        if off < ALIGN or off + n > self.header.payload_end or n > nbytes:
            layout.fail(self.path, f"{self._brick_name(k)}: payload [{off}, +{n}) out of range")
        view = memoryview(self._map)[off:off + n]
        if self.verify_checksums and xxh64(view) != int(en["checksum"]):
            layout.fail(self.path, f"{self._brick_name(k)}: checksum mismatch")
        return view

    def _decompress(self, k, payload, nbytes):
        """One zstd frame, decoded into exactly nbytes (output capacity bounded to it)."""
        try:
            declared = zstandard.frame_content_size(payload)
            if declared not in (-1, nbytes):
                raise zstandard.ZstdError(f"frame declares {declared} bytes")
            # A fresh context per call: contexts are not thread-safe (dask reads from threads).
            out = zstandard.ZstdDecompressor().decompress(payload, max_output_size=nbytes)
        except zstandard.ZstdError as err:
            layout.fail(self.path, f"{self._brick_name(k)}: zstd payload does not decode: {err}")
        if len(out) != nbytes:
            layout.fail(self.path, f"{self._brick_name(k)}: decodes to {len(out)} bytes, "
                                   f"expected {nbytes}")
        return out

    def brick_view(self, c, level, bx, by, bz):
        """Brick (bx, by, bz) of channel c as a read-only array [z, y, x(, component)] of E^3
        voxels, padding replicated (SPEC 'Bricks'); raw bricks are views into the map."""
        k = self.entry_number(c, level, bx, by, bz)
        ch, e = self.channel_infos[c], self.brick_edge
        shape = (e, e, e, ch.components) if ch.components > 1 else (e, e, e)
        nbytes = e ** 3 * ch.brick_bytes_per_voxel
        codec = int(self.index[k]["codec"])
        if self.on_decode is not None:
            self.on_decode(level, ch.name, bx, by, bz, layout.CODEC_NAMES[codec])
        if codec == UNIFORM:
            value = np.frombuffer(self.index[k]["min"].tobytes()[:ch.brick_bytes_per_voxel],
                                  ch.dtype)
            return np.broadcast_to(value.reshape(shape[3:]), shape)
        payload = self._payload(k, nbytes)
        data = payload if codec == RAW else self._decompress(k, payload, nbytes)
        return np.frombuffer(data, ch.dtype).reshape(shape)

    def read_level(self, channel, level=0):
        """A whole level of a channel as a numpy array [z, y, x(, 4)] (old vispack_read API)."""
        c = self.channel_index(channel) if isinstance(channel, str) else channel
        return Channel(self, c).level(level)[...]

    def verify(self):
        """Checks every payload checksum and that all padding is zero; raises VpkError."""
        for k in np.flatnonzero(self.index["codec"] != UNIFORM):
            en = self.index[k]
            off, n = int(en["offset"]), int(en["stored_size"])
            if xxh64(memoryview(self._map)[off:off + n]) != int(en["checksum"]):
                layout.fail(self.path, f"{self._brick_name(int(k))}: checksum mismatch")
        ends = [end for _, end in self._spans]
        starts = [off for off, _ in self._spans[1:]] + [self.header.payload_end]
        gaps = [(128, ALIGN)] + list(zip(ends, starts))
        gaps.append((self.header.meta_off + self.header.meta_size, self.header.index_off))
        for a, b in gaps:
            if any(self._map[a:b]):
                layout.fail(self.path, f"non-zero padding in [{a}, {b})")



class Channel:
    """One channel of a file: name, type, dtype, components; level(L) gives its arrays."""

    def __init__(self, file, c):
        self.file, self.index = file, c
        info = file.channel_infos[c]
        self.name, self.type, self.components = info.name, info.type, info.components
        self.dtype = info.dtype

    def __repr__(self):
        return f"<vispack channel {self.name!r} ({self.type}) of {self.file.path!r}>"

    @property
    def level_count(self):
        """Number of pyramid levels."""
        return len(self.file.levels)

    def level(self, level=0):
        """The Level array of this channel (0 = full resolution; negative counts from the end)."""
        n = len(self.file.levels)
        if not -n <= level < n:
            raise IndexError(f"{self.file.path}: level {level} is outside [0, {n - 1}]")
        return Level(self.file, self.index, level % n)

    @property
    def label_table(self):
        """The metadata's label table (list of {id, name, colour}); empty when absent."""
        return list(self.file.metadata.get("label_table", []))


def _axis_plan(key, size, e):
    """Turns one index (int or slice) on an axis of `size` voxels into (count, squeeze, parts),
    where parts lists (brick, output slice, slice inside the brick) for each brick touched."""
    if isinstance(key, (int, np.integer)):
        i = int(key)
        if not -size <= i < size:
            raise IndexError(f"index {i} is out of bounds for an axis of size {size}")
        key, squeeze = slice(i % size, i % size + 1), True
    elif isinstance(key, slice):
        squeeze = False
    else:
        raise TypeError(f"vispack levels take ints and slices, not {type(key).__name__}")
    start, stop, step = key.indices(size)
    idx = np.arange(start, stop, step, dtype=np.int64)
    parts = []
    if len(idx):
        bricks = idx // e
        cuts = np.flatnonzero(np.diff(bricks)) + 1
        for lo, hi in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(idx)]])):
            b = int(bricks[lo])
            first, last = int(idx[lo]) - b * e, int(idx[hi - 1]) - b * e
            if step > 0:
                inner = slice(first, last + 1, step)
            else:
                inner = slice(first, last - 1 if last > 0 else None, step)
            parts.append((b, slice(int(lo), int(hi)), inner))
    return len(idx), squeeze, parts


def _expand_key(key, ndim):
    """A key as a tuple of ndim entries (Ellipsis expanded, missing axes filled with ':')."""
    key = key if isinstance(key, tuple) else (key,)
    if sum(k is Ellipsis for k in key) > 1:
        raise IndexError("an index can only have a single ellipsis ('...')")
    if any(k is Ellipsis for k in key):
        i = next(j for j, k in enumerate(key) if k is Ellipsis)
        key = key[:i] + (slice(None),) * (ndim - len(key) + 1) + key[i + 1:]
    if len(key) > ndim:
        raise IndexError(f"too many indices: array is {ndim}-dimensional, {len(key)} given")
    return key + (slice(None),) * (ndim - len(key))


class Level:
    """One pyramid level of one channel as a lazy array indexed [z, y, x(, component)].

    Has shape, dtype, ndim, size and nbytes like a numpy array, so dask.array.from_array accepts
    it. Indexing with ints and slices (any step, negative too) returns a numpy array and decodes
    only the bricks the selection covers; level[...] reads the whole level.
    """

    def __init__(self, file, c, level):
        self.file, self.channel_index, self.level = file, c, level
        ch, info = file.channel_infos[c], file.levels[level]
        self.channel = ch.name
        self.dtype = ch.dtype
        dx, dy, dz = info.dims
        self.shape = (dz, dy, dx, ch.components) if ch.components > 1 else (dz, dy, dx)
        self.ndim = len(self.shape)
        self.size = int(np.prod(self.shape, dtype=np.int64))
        self.nbytes = self.size * self.dtype.itemsize
        self.spacing_mm = info.spacing_mm   # (x, y, z) mm
        self.origin_mm = info.origin_mm     # (x, y, z) mm, centre of voxel (0, 0, 0)
        self.brick_edge = file.brick_edge
        self.grid = info.grid[::-1]         # bricks along (z, y, x)

    def __repr__(self):
        return (f"<vispack level {self.level} of channel {self.channel!r}: shape {self.shape} "
                f"[z, y, x{', c' if self.ndim == 4 else ''}], {self.dtype}>")

    def __len__(self):
        return self.shape[0]

    @property
    def chunks(self):
        """One brick per chunk, (z, y, x[, c]): a natural `chunks=` for dask.array.from_array."""
        e = self.brick_edge
        return (e, e, e) + self.shape[3:]

    def __dask_tokenize__(self):
        return ("vispack.Level", self.file._identity, self.channel_index, self.level)

    def __array__(self, dtype=None, copy=None):
        out = self[...]
        return out if dtype is None else out.astype(dtype)

    def __getitem__(self, key):
        """A numpy array of the selected voxels (a copy); decodes only the bricks it needs."""
        key = _expand_key(key, self.ndim)
        e = self.brick_edge
        plans = [_axis_plan(k, n, e) for k, n in zip(key[:3], self.shape[:3])]
        counts = tuple(p[0] for p in plans) + self.shape[3:]
        out = np.empty(counts, self.dtype)
        if all(counts[:3]):
            self._fill(out, plans)
        spatial = tuple(0 if p[1] else slice(None) for p in plans)
        return out[spatial + key[3:]] if self.ndim == 4 else out[spatial]

    def _fill(self, out, plans):
        """Copies every touched brick's part into out (axes z, y, x)."""
        (_, _, zparts), (_, _, yparts), (_, _, xparts) = plans
        for bz, oz, iz in zparts:
            for by, oy, iy in yparts:
                for bx, ox, ix in xparts:
                    brick = self.file.brick_view(self.channel_index, self.level, bx, by, bz)
                    out[oz, oy, ox] = brick[iz, iy, ix]
