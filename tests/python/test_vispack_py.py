#!/usr/bin/python3
"""Tests of the `vispack` Python package (python/vispack/) against the C++ tools.

Run by ctest (tests/python/CMakeLists.txt) as
    /usr/bin/python3 tests/python/test_vispack_py.py
with VISPACK_BIN_DIR set to the build's bin/ folder. It makes its own packed files: the `tiny`
phantom (vispack-phantom) packed by vispack-run with 8-voxel bricks (config edited) so every level
has many bricks, once with zstd and once uncompressed (raw bricks); vispack-extract (the C++
reader) gives the reference decode of every level and channel. Arrays are indexed
[z, y, x(, component)], as the package returns them.
Exits 77 (ctest: skipped) when numpy or zstandard (Debian's packages) are missing, and 1 when
the `vispack` package itself fails to import (a broken package is a failure, not a skip). Under CI
(CI=true) or VISPACK_STRICT=1 the optional packages (python3-dask, python3-xxhash) must be present
too: their tests fail instead of skipping.
"""
import gzip
import itertools
import json
import os
import pickle
import shutil
import struct
import subprocess
import sys
import tempfile
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE_DIR = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(SOURCE_DIR, "python"))

STRICT = os.environ.get("CI") == "true" or os.environ.get("VISPACK_STRICT") == "1"

try:
    import numpy as np
    import zstandard
except ImportError as err:  # pragma: no cover - depends on the machine
    print(f"test_vispack_py: skipped: {err} (install python3-numpy python3-zstandard)")
    sys.exit(77)

# Our own package: an import error here is a defect of python/vispack, never a skip.
import vispack  # noqa: E402
from vispack import checksum, layout  # noqa: E402

try:
    import dask.array as da
except ImportError:  # pragma: no cover
    if STRICT:
        print("test_vispack_py: python3-dask is not installed, and under CI its tests must run "
              "(scripts/install-deps.sh installs it)")
        sys.exit(1)
    da = None

BRICK_EDGE = 8
NRRD_TYPES = {"int16": "<i2", "short": "<i2", "uint8": "u1", "unsigned char": "u1", "uchar": "u1",
              "uint16": "<u2", "unsigned short": "<u2", "ushort": "<u2"}


def bin_dir():
    """The build's bin/ folder (VISPACK_BIN_DIR, else build/bin under the source tree)."""
    return os.environ.get("VISPACK_BIN_DIR", os.path.join(SOURCE_DIR, "build", "bin"))


def run_tool(name, *args):
    """Runs a vispack tool from bin_dir(); raises with its stderr when it fails."""
    p = subprocess.run([os.path.join(bin_dir(), name), *args], capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{name} {' '.join(args)} exited {p.returncode}: {p.stderr}")
    return p


def read_bytes(path):
    """The whole file as bytes."""
    with open(path, "rb") as fh:
        return fh.read()


def read_nrrd(path):
    """A NRRD written by vispack (raw or gzip) as an array [z, y, x(, component)]."""
    head, _, body = read_bytes(path).partition(b"\n\n")
    fields = dict(line.split(": ", 1) for line in head.decode().splitlines()[1:]
                  if ": " in line)
    sizes = [int(v) for v in fields["sizes"].split()]
    if fields["encoding"] == "gzip":
        body = gzip.decompress(body)
    arr = np.frombuffer(body, NRRD_TYPES[fields["type"]])
    return arr.reshape(sizes[::-1])  # NRRD sizes are fastest first


def edit_config(config_path, output, zstd_level):
    """Points the phantom's config at output with 8-voxel bricks, no OpenVDB export."""
    with open(config_path) as fh:
        config = json.load(fh)
    config["output"] = output
    config.setdefault("pack", {}).update(brick_edge=BRICK_EDGE, zstd_level=zstd_level)
    config.setdefault("vdb", {})["enabled"] = False
    with open(config_path, "w") as fh:
        json.dump(config, fh, indent=1)


def make_volumes(folder):
    """Phantom `tiny` packed twice with 8-voxel bricks: zstd (level 3) and uncompressed (every
    non-uniform brick raw); returns the two .vpk paths."""
    run_tool("vispack-phantom", "--out", folder, "--preset", "tiny")
    config_path = os.path.join(folder, "config.json")
    zstd_path, raw_path = os.path.join(folder, "tiny.vpk"), os.path.join(folder, "tiny-raw.vpk")
    edit_config(config_path, zstd_path, 3)
    run_tool("vispack-run", config_path, "--quiet")
    edit_config(config_path, raw_path, 0)
    run_tool("vispack-run", config_path, "--quiet", "--from", "pack", "--to", "pack")
    return zstd_path, raw_path


def random_box(rng, shape, e):
    """A random [z, y, x] key of slices: some cross a brick border, some end at the volume edge,
    some are single voxels (ints), some have steps."""
    key = []
    for n in shape[:3]:
        kind = rng.integers(0, 6)
        if kind == 0:    # around a brick border
            border = int(rng.integers(0, -(-n // e) + 1)) * e
            a = max(0, border - int(rng.integers(1, e)))
            b = min(n, border + int(rng.integers(1, e)))
            key.append(slice(min(a, n - 1), max(b, min(a, n - 1) + 1)))
        elif kind == 1:  # touching the volume edge
            key.append(slice(int(rng.integers(0, n)), n))
        elif kind == 2:  # one voxel
            key.append(int(rng.integers(-n, n)))
        elif kind == 3:  # a step, possibly negative
            step = int(rng.choice([2, 3, e + 1, -1, -3]))
            a, b = sorted(int(v) for v in rng.integers(0, n + 1, 2))
            key.append(slice(a, b, step) if step > 0 else slice(b, a, step))
        else:            # anywhere, negative bounds allowed
            a = int(rng.integers(-n, n))
            key.append(slice(a, a + int(rng.integers(1, n + 1))))
    return tuple(key)


def bricks_of(key, shape, e):
    """The set of (bx, by, bz) bricks a [z, y, x] key covers (independent of the reader)."""
    per_axis = []
    for k, n in zip(key, shape[:3]):
        idx = [k % n] if isinstance(k, int) else list(range(*k.indices(n)))
        per_axis.append(sorted({i // e for i in idx}))
    bz, by, bx = per_axis
    return {(x, y, z) for z in bz for y in by for x in bx}


def build_fixture(folder):
    """Packs the phantom into folder and decodes every level and channel with vispack-extract;
    returns (zstd path, raw path, channel names, level count,
    {(channel, level): reference array})."""
    for tool in ("vispack-phantom", "vispack-run", "vispack-extract"):
        if not os.access(os.path.join(bin_dir(), tool), os.X_OK):
            raise unittest.SkipTest(f"{tool} is not built in {bin_dir()}")
    path, raw_path = make_volumes(os.path.join(folder, "tiny"))
    with vispack.open(path) as f:
        channels, level_count = f.channel_names, f.level_count
    reference = {}
    for name, level in itertools.product(channels, range(level_count)):
        out = os.path.join(folder, f"{name}{level}.nrrd")
        run_tool("vispack-extract", path, "--channel", name, "--level", str(level), "-o", out)
        reference[name, level] = read_nrrd(out)
    return path, raw_path, channels, level_count, reference


_FIXTURE = {}  # built once for all test classes (setUpModule), removed by tearDownModule


def setUpModule():
    _FIXTURE["tmp"] = tempfile.mkdtemp(prefix="vispack_py_")
    try:
        _FIXTURE["volume"] = build_fixture(_FIXTURE["tmp"])
    except BaseException:  # tearDownModule does not run when setUpModule fails
        shutil.rmtree(_FIXTURE.pop("tmp"), ignore_errors=True)
        raise


def tearDownModule():
    if os.environ.get("VISPACK_KEEP_TEMP"):
        print(f"kept {_FIXTURE.get('tmp')}")
        return
    shutil.rmtree(_FIXTURE.pop("tmp", ""), ignore_errors=True)


class PackedVolume(unittest.TestCase):
    """Base: the shared packed phantom (path: zstd bricks, raw_path: raw bricks) and the C++
    decode of path (reference)."""

    @classmethod
    def setUpClass(cls):
        cls.tmp = _FIXTURE["tmp"]
        cls.path, cls.raw_path, cls.channels, cls.level_count, cls.reference = _FIXTURE["volume"]

    def copy_with(self, edit, name):
        """A copy of the packed file with edit(bytearray) applied; returns its path."""
        data = bytearray(read_bytes(self.path))
        edit(data)
        out = os.path.join(self.tmp, name)
        with open(out, "wb") as fh:
            fh.write(data)
        return out


class Regions(PackedVolume):
    """Regions equal the C++ full-level decode voxel for voxel."""

    def test_fixture_has_many_bricks(self):
        for path, codec in ((self.path, layout.ZSTD), (self.raw_path, layout.RAW)):
            with vispack.open(path) as f:
                self.assertEqual(f.brick_edge, BRICK_EDGE)
                self.assertGreaterEqual(self.level_count, 3)
                self.assertGreater(min(f["ct"].level(0).grid), 1)
                self.assertIn(codec, set(f.index["codec"].tolist()), path)

    def test_whole_levels_match(self):
        for path in (self.path, self.raw_path):
            with vispack.open(path, verify_checksums=True) as f:
                for (name, level), ref in self.reference.items():
                    lv = f[name].level(level)
                    self.assertEqual(lv.shape, ref.shape, (name, level))
                    self.assertEqual(lv.dtype, ref.dtype)
                    self.assertEqual(lv.ndim, ref.ndim)
                    np.testing.assert_array_equal(lv[...], ref, err_msg=f"{path} {name} {level}")
                    np.testing.assert_array_equal(np.asarray(lv), ref)

    def test_random_boxes_match(self):
        rng = np.random.default_rng(13)
        for path in (self.path, self.raw_path):
            with vispack.open(path) as f:
                for (name, level), ref in self.reference.items():
                    lv = f[name].level(level)
                    for _ in range(60):
                        key = random_box(rng, lv.shape, BRICK_EDGE)
                        if lv.ndim == 4 and rng.integers(0, 3) == 0:
                            key += (int(rng.integers(0, 4)),)
                        got = lv[key]
                        self.assertEqual(got.shape, ref[key].shape, (name, level, key))
                        np.testing.assert_array_equal(got, ref[key],
                                                      err_msg=f"{path} {name} {level} {key}")

    def test_brick_borders_and_edges(self):
        """Boxes from one voxel before each brick border (on each axis) to the volume's end, and
        the last voxel."""
        e = BRICK_EDGE
        with vispack.open(self.path) as f:
            for (name, level), ref in self.reference.items():
                lv = f[name].level(level)
                for axis in range(3):
                    n = lv.shape[axis]
                    for b in range(1, -(-n // e)):
                        key = [slice(None)] * 3
                        key[axis] = slice(b * e - 1, n)
                        key[(axis + 1) % 3] = slice(b * e - 1 if b * e < lv.shape[(axis + 1) % 3]
                                                    else 0, None)
                        key = tuple(key)
                        np.testing.assert_array_equal(lv[key], ref[key],
                                                      err_msg=f"{name} {level} {key}")
                last = tuple(n - 1 for n in lv.shape[:3])
                np.testing.assert_array_equal(lv[last], ref[last])
                np.testing.assert_array_equal(lv[-1:, -1:, -1:], ref[-1:, -1:, -1:])
                self.assertEqual(lv[0:0, :, :].shape, ref[0:0, :, :].shape)

    def test_bad_keys(self):
        with vispack.open(self.path) as f:
            lv = f["ct"].level(0)
            with self.assertRaises(IndexError):
                lv[lv.shape[0]]
            with self.assertRaises(IndexError):
                lv[0, 0, 0, 0]
            with self.assertRaises(TypeError):
                lv[[1, 2]]
            with self.assertRaises(KeyError):
                f["nope"]
            with self.assertRaises(IndexError):
                f["ct"].level(self.level_count)


class LazyDecoding(PackedVolume):
    """Only the bricks a region covers are decoded, each once."""

    def open_counting(self):
        touched = []
        f = vispack.open(self.path, on_decode=lambda *brick: touched.append(brick))
        return f, touched

    def test_region_decodes_only_its_bricks(self):
        rng = np.random.default_rng(7)
        f, touched = self.open_counting()
        with f:
            for name, level in itertools.product(self.channels, range(self.level_count)):
                lv = f[name].level(level)
                for _ in range(20):
                    key = random_box(rng, lv.shape, BRICK_EDGE)
                    touched.clear()
                    lv[key]
                    got = [(bx, by, bz) for (lvl, ch, bx, by, bz, _) in touched
                           if (lvl, ch) == (level, name)]
                    self.assertEqual(len(got), len(touched))
                    self.assertEqual(len(got), len(set(got)), f"a brick decoded twice for {key}")
                    self.assertEqual(set(got), bricks_of(key, lv.shape, BRICK_EDGE), key)

    def test_small_region_of_a_big_level(self):
        f, touched = self.open_counting()
        with f:
            lv = f["rgba"].level(0)
            lv[3, 5, 9]
            self.assertEqual([t[2:5] for t in touched], [(1, 0, 0)])
            touched.clear()
            lv[0:BRICK_EDGE, 0:BRICK_EDGE, 0:2 * BRICK_EDGE]
            self.assertEqual(len(touched), 2)
            touched.clear()
            lv[:, :, ::2 * BRICK_EDGE]  # every other brick column
            gz, gy, gx = lv.grid
            self.assertEqual(len(touched), gz * gy * -(-gx // 2))
            touched.clear()
            lv[0:0]
            self.assertEqual(touched, [])


@unittest.skipIf(da is None, "python3-dask is not installed")
class Dask(PackedVolume):
    """dask.array.from_array accepts a Level and computes the same results."""

    def test_sums(self):
        with vispack.open(self.path) as f:
            for (name, level), ref in self.reference.items():
                lv = f[name].level(level)
                for chunks in (lv.chunks, (5, 7, 9) + lv.shape[3:]):
                    d = da.from_array(lv, chunks=chunks)
                    self.assertEqual(d.shape, ref.shape)
                    self.assertEqual(d.dtype, ref.dtype)
                    total = int(d.sum(dtype=np.int64).compute())
                    self.assertEqual(total, int(ref.sum(dtype=np.int64)), (name, level, chunks))
                per_slice = da.from_array(lv, chunks=lv.chunks).sum(axis=(1, 2), dtype=np.int64)
                np.testing.assert_array_equal(per_slice.compute(),
                                              ref.sum(axis=(1, 2), dtype=np.int64))

    def test_region_of_dask_array_and_pickle(self):
        with vispack.open(self.path) as f:
            lv = f["ct"].level(0)
            ref = self.reference["ct", 0]
            d = da.from_array(lv, chunks=lv.chunks)
            np.testing.assert_array_equal(d[3:17, 5:40:3, -20:].compute(), ref[3:17, 5:40:3, -20:])
            clone = pickle.loads(pickle.dumps(lv))  # what dask.distributed ships to workers
            np.testing.assert_array_equal(clone[2:9], ref[2:9])
            clone.file.close()


class Hostile(PackedVolume):
    """Truncated, corrupted and hostile files raise a clear VpkError, never crash."""

    def zstd_entry(self, f):
        """(k, level, channel name, bx, by, bz) of the first zstd brick."""
        k = int(np.flatnonzero(f.index["codec"] == layout.ZSTD)[0])
        en = f.index[k]
        return k, int(en["level"]), f.channel_names[en["channel"]], int(en["bx"]), \
            int(en["by"]), int(en["bz"])

    def with_table_checksum(self, data):
        """Recomputes the header's table checksum, so only the deeper checks can catch an edit."""
        meta_off = struct.unpack_from("<Q", data, 40)[0]  # header field metadata_offset
        table = checksum.xxh64(bytes(data[:120]) + bytes(data[meta_off:]))
        struct.pack_into("<Q", data, 120, table)

    def assert_error(self, path, *words, **open_args):
        with self.assertRaises(vispack.VpkError) as cm:
            vispack.open(path, **open_args)
        for w in words:
            self.assertIn(w, str(cm.exception))
        self.assertIn(path, str(cm.exception))
        return cm.exception

    def test_truncated(self):
        short = self.copy_with(lambda d: d.__delitem__(slice(len(d) - 100, None)), "short.vpk")
        self.assert_error(short, "truncated")
        tiny = self.copy_with(lambda d: d.__delitem__(slice(50, None)), "tiny.vpk")
        self.assert_error(tiny, "truncated")
        empty = self.copy_with(lambda d: d.clear(), "empty.vpk")
        self.assert_error(empty, "truncated")

    def test_header_and_table(self):
        def magic(d):
            d[1] = ord("X")
        self.assert_error(self.copy_with(magic, "magic.vpk"), "bad magic")

        def meta(d):
            h = layout.parse_header(bytes(d), len(d), "x")
            d[h.meta_off + 3] ^= 0x20
        self.assert_error(self.copy_with(meta, "meta.vpk"), "table checksum")

    def test_corrupted_payload(self):
        with vispack.open(self.path) as f:
            k, level, name, bx, by, bz = self.zstd_entry(f)
            off = int(f.index[k]["offset"])
        bad = self.copy_with(lambda d: d.__setitem__(off + 5, d[off + 5] ^ 0xFF), "payload.vpk")
        region = (slice(bz * BRICK_EDGE, (bz + 1) * BRICK_EDGE),
                  slice(by * BRICK_EDGE, (by + 1) * BRICK_EDGE),
                  slice(bx * BRICK_EDGE, (bx + 1) * BRICK_EDGE))
        with vispack.open(bad, verify_checksums=True) as f:
            with self.assertRaises(vispack.VpkError) as cm:
                f[name].level(level)[region]
            self.assertIn(f"level {level} channel {name} brick ({bx},{by},{bz})", str(cm.exception))
            self.assertIn("checksum mismatch", str(cm.exception))
            with self.assertRaises(vispack.VpkError):
                f.verify()
        script = os.path.join(SOURCE_DIR, "scripts", "vispack_read.py")
        cli = subprocess.run([sys.executable, script, "--verify", bad], capture_output=True,
                             text=True)
        self.assertEqual(cli.returncode, 4, cli.stderr)
        self.assertIn("checksum mismatch", cli.stderr)

    def test_index_entry_outside_the_file(self):
        with vispack.open(self.path) as f:
            k, level, name, bx, by, bz = self.zstd_entry(f)
            at = f.header.index_off + 64 * k
        where = f"level {level} channel {name} brick ({bx},{by},{bz})"
        for field, value in ((16, 1 << 40), (16, 2**64 - 4096), (24, 2**63), (24, 0)):
            def edit(d, field=field, value=value):
                struct.pack_into("<Q", d, at + field, value)
                self.with_table_checksum(d)
            self.assert_error(self.copy_with(edit, "entry.vpk"), where)

        def codec(d):
            d[at + 14] = 9
            self.with_table_checksum(d)
        self.assert_error(self.copy_with(codec, "codec.vpk"), where, "unknown codec")

        def moved(d):
            struct.pack_into("<I", d, at, 1000)
            self.with_table_checksum(d)
        self.assert_error(self.copy_with(moved, "moved.vpk"), "out of place")

    def test_zstd_frames_of_the_wrong_size(self):
        """Valid zstd frames (checksums fixed up) that decode to too few bytes, or declare 1 TiB
        (a reader trusting the frame header would try to allocate it)."""
        with vispack.open(self.path) as f:
            k, level, name, bx, by, bz = self.zstd_entry(f)
            en = f.index[k]
            off, n, at = int(en["offset"]), int(en["stored_size"]), f.header.index_off + 64 * k
        short = zstandard.ZstdCompressor(write_checksum=False).compress(b"\x01" * 40)
        self.assertEqual(short[4], 0x20)  # single segment, 1-byte content size (40)
        huge = short[:4] + bytes([0xE0]) + struct.pack("<Q", 1 << 40) + short[6:]
        self.assertEqual(zstandard.frame_content_size(huge), 1 << 40)
        for frame in (short, huge):
            self.assertLess(len(frame), n)

            def edit(d, frame=frame):
                d[off:off + n] = frame + bytes(n - len(frame))
                struct.pack_into("<QQ", d, at + 24, len(frame), checksum.xxh64(frame))
                self.with_table_checksum(d)
            bad = self.copy_with(edit, "frame.vpk")
            with vispack.open(bad, verify_checksums=True) as f:
                with self.assertRaises(vispack.VpkError) as cm:
                    f[name].level(level)[...]
                self.assertIn(f"level {level} channel {name} brick ({bx},{by},{bz})",
                              str(cm.exception))

    def test_random_mutations_never_crash(self):
        """Random bytes of header, metadata, index and label IDs changed (table checksum fixed up
        so the deeper checks are reached): opening and reading everything either works or raises
        VpkError; nothing else escapes."""
        rng = np.random.default_rng(99)
        good = read_bytes(self.path)
        h = layout.parse_header(good, len(good), "x")
        areas = [(8, 120), (h.meta_off, h.index_off), (h.index_off, h.file_size)]
        out = os.path.join(self.tmp, "mutant.vpk")
        outcomes = {"ok": 0, "error": 0}
        for i in range(150):
            data = bytearray(good)
            a, b = areas[i % len(areas)]
            for _ in range(int(rng.integers(1, 4))):
                data[int(rng.integers(a, b))] = int(rng.integers(0, 256))
            self.with_table_checksum(data)
            with open(out, "wb") as fh:
                fh.write(data)
            try:
                with vispack.open(out, verify_checksums=bool(i % 2)) as f:
                    for name in f:
                        for level in range(f.level_count):
                            f[name].level(level)[...]
                outcomes["ok"] += 1
            except vispack.VpkError:
                outcomes["error"] += 1
        self.assertGreater(outcomes["error"], 50, outcomes)


class Checksums(PackedVolume):
    """The table checksum, payload checksums and the two xxh64 implementations."""

    def test_verify_good_file(self):
        with vispack.open(self.path) as f:
            f.verify()

    def test_pure_python_matches_fast(self):
        if not checksum.have_fast_xxh64():
            if STRICT:
                self.fail("python3-xxhash is not installed, and under CI this test must run")
            self.skipTest("python3-xxhash is not installed")
        rng = np.random.default_rng(3)
        for n in (0, 1, 3, 4, 7, 8, 31, 32, 33, 100, 4096):
            data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
            self.assertEqual(checksum.xxh64_pure(data), checksum.xxh64(data), n)


class CommandLine(PackedVolume):
    """scripts/vispack_read.py, the thin command line over the package."""

    def test_region_dump(self):
        out = os.path.join(self.tmp, "region.bin")
        script = os.path.join(SOURCE_DIR, "scripts", "vispack_read.py")
        p = subprocess.run([sys.executable, script, self.path, "--channel", "ct", "--level", "1",
                            "--region", "2:9,5:,::2", "--raw", out], capture_output=True, text=True)
        self.assertEqual(p.returncode, 0, p.stderr)
        ref = self.reference["ct", 1][2:9, 5:, ::2]
        got = np.fromfile(out, "<i2")
        np.testing.assert_array_equal(got, ref.ravel())
        # One line names the file written, with what it holds.
        self.assertEqual(p.stdout.splitlines()[-1],
                         f"wrote {out} (ct, level 1, shape [z, y, x] {list(ref.shape)}, <i2)")
        p = subprocess.run([sys.executable, script, self.path, "--channel", "nope", "--raw", out],
                           capture_output=True, text=True)
        self.assertEqual(p.returncode, 2, p.stderr)


if __name__ == "__main__":
    unittest.main(verbosity=2)
