#!/usr/bin/python3
"""vispack-export's OME-Zarr, read back by readers vispack did not write.

Run by ctest (tests/python/CMakeLists.txt) as
    /usr/bin/python3 tests/python/test_ome_zarr.py 0.4|0.5
with VISPACK_BIN_DIR (vispack-export, vispack-extract, vispack-info) and VISPACK_MAKE_SAMPLE
(tests/format/make_sample.cpp) set. NGFF 0.4 (Zarr v2) is read with Debian's python3-zarr; 0.5
(Zarr v3, sharded) with zarrita from npm (node tests/js/read_zarr.mjs; scripts/fetch-js-deps.sh).
Every level of every exported image must equal, bit for bit, what vispack-extract writes as NRRD
for the same level and channel (colour = r, g, b of the rgba channel on a leading axis, alpha its
component 3). The metadata is checked against OME-NGFF's required fields (written here from the
specification's text: axes, multiscales datasets and transforms, omero, labels and image-label)
and the transforms against the packed file's spacing and origin (SPEC.md "Levels of detail").
Inputs: small volumes from format_make_sample, odd on purpose: dims not multiples of the brick
edge, a volume of one brick, uint16 labels with 725 IDs, an empty label table, raw bricks.
Exits 77 (ctest: skipped; under CI a failure, scripts/test.sh) when a reader is missing.
"""
import glob
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE_DIR = os.path.normpath(os.path.join(HERE, "..", ".."))
NGFF = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] in ("0.4", "0.5") else "0.4"
if len(sys.argv) > 1 and sys.argv[1] in ("0.4", "0.5"):
    del sys.argv[1]
JS_READER = os.path.join(SOURCE_DIR, "tests", "js", "read_zarr.mjs")
JS_MODULES = os.path.join(SOURCE_DIR, "tests", "js", "node_modules", "zarrita")

try:
    import numpy as np
    if NGFF == "0.4":
        import zarr
except ImportError as err:  # pragma: no cover - depends on the machine
    print(f"test_ome_zarr: skipped: {err} (install python3-numpy python3-zarr)")
    sys.exit(77)
if NGFF == "0.5" and (shutil.which("node") is None or not os.path.isdir(JS_MODULES)):
    print("test_ome_zarr: skipped: node or zarrita missing (scripts/install-deps.sh, "
          "scripts/fetch-js-deps.sh)")
    sys.exit(77)

NRRD_TYPES = {"int16": "<i2", "short": "<i2", "uint8": "u1", "unsigned char": "u1",
              "uchar": "u1", "uint16": "<u2", "unsigned short": "<u2", "ushort": "<u2"}
V3_TYPES = {"uint8": "u1", "int16": "<i2", "uint16": "<u2"}
SPACE_UNITS = {"angstrom", "attometer", "centimeter", "decimeter", "exameter", "femtometer",
               "foot", "gigameter", "hectometer", "inch", "kilometer", "megameter", "meter",
               "micrometer", "mile", "millimeter", "nanometer", "parsec", "petameter",
               "picometer", "terameter", "yard", "yoctometer", "yottameter", "zeptometer",
               "zettameter"}
SHARD_BRICKS = 2  # small shards, so the test volumes have several


def bin_dir():
    return os.environ.get("VISPACK_BIN_DIR", os.path.join(SOURCE_DIR, "build", "bin"))


def run(args, check=True):
    p = subprocess.run(args, capture_output=True, text=True)
    if check and p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} exited {p.returncode}: {p.stderr}")
    return p


def tool(name):
    return os.path.join(bin_dir(), name)


def read_nrrd(path):
    """A raw NRRD written by vispack-extract: (array [z, y, x(, component)], header fields)."""
    with open(path, "rb") as fh:
        head, _, body = fh.read().partition(b"\n\n")
    fields = dict(line.split(": ", 1) for line in head.decode().splitlines()[1:] if ": " in line)
    sizes = [int(v) for v in fields["sizes"].split()]
    assert fields["encoding"] == "raw"
    return np.frombuffer(body, NRRD_TYPES[fields["type"]]).reshape(sizes[::-1]), fields


def nrrd_origin(fields):
    return [float(v) for v in re.findall(r"[-+0-9.eE]+", fields["space origin"])]


def crc32c(data):
    """CRC-32C (Castagnoli), bit by bit: independent of the exporter's table version."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


class Export:
    """One exported volume: the store, its metadata as the version stores it, and readers."""

    def __init__(self, root):
        self.root = root

    def group_attrs(self, path):
        """The OME-NGFF attributes of a group and the version they claim."""
        if NGFF == "0.4":
            with open(os.path.join(self.root, path, ".zattrs")) as fh:
                attrs = json.load(fh)
            with open(os.path.join(self.root, path, ".zgroup")) as fh:
                assert json.load(fh) == {"zarr_format": 2}
            return attrs
        with open(os.path.join(self.root, path, "zarr.json")) as fh:
            doc = json.load(fh)
        assert doc["zarr_format"] == 3 and doc["node_type"] == "group", doc
        return doc["attributes"].get("ome", doc["attributes"])

    def array_meta(self, path):
        name = ".zarray" if NGFF == "0.4" else "zarr.json"
        with open(os.path.join(self.root, path, name)) as fh:
            return json.load(fh)

    def read_all(self, paths, tmp):
        """Whole arrays through the independent reader: {path: numpy array}."""
        if NGFF == "0.4":
            return {p: zarr.open_array(os.path.join(self.root, p), mode="r")[...] for p in paths}
        infos = json.loads(run(["node", JS_READER, self.root, tmp, *paths]).stdout)
        out = {}
        for i, (path, info) in enumerate(zip(paths, infos)):
            data = np.fromfile(os.path.join(tmp, f"{i}.bin"), V3_TYPES[info["data_type"]])
            out[path] = data.reshape(info["shape"])
        return out


class OmeZarrTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="vispack-ome-zarr-")
        cls.sample_tool = os.environ.get("VISPACK_MAKE_SAMPLE", "")
        if not os.path.exists(cls.sample_tool):
            raise unittest.SkipTest("VISPACK_MAKE_SAMPLE (format_make_sample) is not set")

    @classmethod
    def tearDownClass(cls):
        if not os.environ.get("VISPACK_KEEP_TEST_DIRS"):
            shutil.rmtree(cls.tmp, ignore_errors=True)

    def make(self, name, *sample_args):
        vpk = os.path.join(self.tmp, name + ".vpk")
        run([self.sample_tool, vpk, *sample_args])
        return vpk

    def export(self, vpk, name, *args):
        out = os.path.join(self.tmp, name + ".zarr")
        extra = ["--shard-bricks", str(SHARD_BRICKS)] if NGFF == "0.5" else []
        run([tool("vispack-export"), vpk, "--ome-zarr", out, "--ngff", NGFF, "--quiet",
             "--threads", "2", *extra, *args])
        self.assertEqual(glob.glob(out + ".partial-*"), [], "a partial folder was left")
        return Export(out)

    def info(self, vpk):
        return json.loads(run([tool("vispack-info"), vpk, "--json"]).stdout)["metadata"]

    def extract(self, vpk, channel, level):
        """vispack-extract's NRRD of one channel and level (once per file, channel and level)."""
        out = os.path.join(self.tmp, f"{os.path.basename(vpk)}_{channel}_{level}.nrrd")
        if not os.path.exists(out):
            run([tool("vispack-extract"), vpk, "--channel", channel, "--level", str(level),
                 "-o", out])
        return read_nrrd(out)

    # ---- metadata rules of OME-NGFF (0.4 and 0.5 "multiscales", "omero", labels) ----

    def check_multiscales(self, ex, path, meta, expect_levels):
        attrs = ex.group_attrs(path)
        if NGFF == "0.5":
            self.assertEqual(attrs.get("version"), "0.5")
        ms_list = attrs["multiscales"]
        self.assertIsInstance(ms_list, list)
        self.assertGreaterEqual(len(ms_list), 1)
        ms = ms_list[0]
        if NGFF == "0.4":
            self.assertEqual(ms["version"], "0.4")
        else:
            self.assertNotIn("version", ms)
        axes = ms["axes"]
        self.assertTrue(2 <= len(axes) <= 5, axes)
        names = [a["name"] for a in axes]
        self.assertEqual(len(set(names)), len(names), "axis names must be unique")
        types = [a.get("type") for a in axes]
        self.assertIn(types.count("space"), (2, 3))
        order = {"time": 0, "channel": 1, "space": 2}
        ranks = [order[t] for t in types]
        self.assertEqual(ranks, sorted(ranks), "time, then channel, then space axes")
        for a in axes:
            if a["type"] == "space":
                self.assertIn(a["unit"], SPACE_UNITS)
        self.assertEqual(names[-3:], ["z", "y", "x"])
        datasets = ms["datasets"]
        self.assertEqual([d["path"] for d in datasets], [str(lv) for lv in expect_levels])
        spacing0 = meta["spacing_mm"]
        origin0 = meta["origin_mm"]
        prev = None
        for d, level in zip(datasets, expect_levels):
            ts = d["coordinateTransformations"]
            self.assertEqual(ts[0]["type"], "scale", "the first transform is a scale")
            self.assertLessEqual(len(ts), 2)
            self.assertEqual(len(ts[0]["scale"]), len(axes))
            if len(ts) == 2:
                self.assertEqual(ts[1]["type"], "translation")
                self.assertEqual(len(ts[1]["translation"]), len(axes))
            scale, translation = ts[0]["scale"][-3:], ts[1]["translation"][-3:]
            # SPEC.md: level L spacing spacing0 * 2^L; origin origin0 + (2^L - 1) / 2 * spacing0
            # (voxel centres), z, y, x order here.
            for k, axis in enumerate((2, 1, 0)):
                self.assertAlmostEqual(scale[k], spacing0[axis] * 2 ** level, places=9)
                self.assertAlmostEqual(translation[k],
                                       origin0[axis] + (2 ** level - 1) / 2 * spacing0[axis],
                                       places=9)
            self.assertTrue(all(s > 0 for s in ts[0]["scale"]))
            if prev is not None:  # highest resolution first
                self.assertTrue(all(b >= a for a, b in zip(prev, ts[0]["scale"])))
            prev = ts[0]["scale"]
            am = ex.array_meta(f"{path}/{d['path']}")
            shape = am["shape"]
            self.assertEqual(len(shape), len(axes), "array dimensions equal the axes")
            if NGFF == "0.4":
                self.assertEqual(am["dimension_separator"], "/")
                self.assertEqual(am["compressor"]["id"], "zstd")
            else:
                self.assertEqual(am["dimension_names"], names)
                self.assertEqual(am["codecs"][0]["name"], "sharding_indexed")
        return attrs, ms

    def check_omero(self, attrs, channels):
        omero = attrs["omero"]
        self.assertEqual(len(omero["channels"]), channels)
        for ch in omero["channels"]:
            self.assertRegex(ch["color"], r"^[0-9A-F]{6}$")
            for key in ("min", "max", "start", "end"):
                self.assertIsInstance(ch["window"][key], (int, float))

    def check_image_label(self, attrs, meta, has_source):
        il = attrs["image-label"]
        if NGFF == "0.4":
            self.assertEqual(il["version"], "0.4")
        table = meta.get("label_table", [])
        colours = {c["label-value"]: c["rgba"] for c in il["colors"]}
        for c in il["colors"]:
            self.assertIsInstance(c["label-value"], int)
            self.assertEqual(len(c["rgba"]), 4)
            self.assertTrue(all(0 <= v <= 255 and isinstance(v, int) for v in c["rgba"]))
        names = {p["label-value"]: p["name"] for p in il["properties"]}
        self.assertEqual(len(names), len(table))
        for e in table:
            self.assertEqual(names[e["id"]], e["name"])
            self.assertEqual(colours[e["id"]], e["colour"] + [255])
        self.assertEqual(colours[0], [0, 0, 0, 0])
        if has_source:
            self.assertEqual(il["source"], {"image": "../../"})

    # ---- the data, against vispack-extract ----

    def check_volume(self, vpk, name, *export_args, channels=("rgba", "ct", "labels"),
                     levels=None):
        ex = self.export(vpk, name, *export_args)
        meta = self.info(vpk)
        level_count = len(meta["levels"])
        levels = list(range(level_count)) if levels is None else levels
        root = ex.group_attrs("")
        if NGFF == "0.5":
            with open(os.path.join(ex.root, "zarr.json")) as fh:
                root = json.load(fh)["attributes"]
        images = {im["path"]: im for im in root["vispack"]["images"]}
        expected = {"rgba": ["rgb", "alpha"], "ct": ["ct"], "labels": ["rgb/labels/labels"]}
        want = [p for c in channels for p in expected[c]]
        if "rgba" not in channels and "labels" in channels:
            want = [p if p != "rgb/labels/labels" else
                    ("ct/labels/labels" if "ct" in channels else "labels") for p in want]
        self.assertEqual(sorted(images), sorted(want))
        tmp = tempfile.mkdtemp(dir=self.tmp)
        arrays = ex.read_all([f"{p}/{lv}" for p in images for lv in levels], tmp)
        checked = 0
        for path, im in images.items():
            attrs, ms = self.check_multiscales(ex, path, meta, levels)
            if im["kind"] == "labels":
                self.check_image_label(attrs, meta, path != "labels")
                self.assertNotIn("omero", attrs)
                host = path.split("/labels/")[0] if "/labels/" in path else None
                if host:
                    self.assertEqual(ex.group_attrs(host + "/labels")["labels"], ["labels"])
            else:
                self.check_omero(attrs, 3 if im["kind"] == "colour" else 1)
            for level in levels:
                ref, fields = self.extract(vpk, im["channel"], level)
                if im["kind"] == "colour":
                    ref = np.moveaxis(ref[..., :3], -1, 0)
                elif im["kind"].startswith("alpha"):
                    ref = ref[..., 3]
                got = arrays[f"{path}/{level}"]
                self.assertEqual(got.shape, ref.shape, f"{path} level {level}")
                self.assertEqual(got.dtype, ref.dtype, f"{path} level {level}")
                self.assertTrue(np.array_equal(got, ref), f"{path} level {level} differs")
                # The NRRD's origin (vispack-extract) is the dataset's translation.
                ds = ms["datasets"][levels.index(level)]
                self.assertEqual([round(v, 9) for v in
                                  ds["coordinateTransformations"][1]["translation"][-3:]],
                                 [round(v, 9) for v in nrrd_origin(fields)[::-1]])
                checked += 1
        if NGFF == "0.5":
            self.check_shards(ex, images, levels, meta)
        return ex, checked

    def check_shards(self, ex, images, levels, meta):
        """One file per shard (none per brick), each ending with its index and crc32c."""
        e = meta["brick_edge"]
        for path in images:
            for level in levels:
                am = ex.array_meta(f"{path}/{level}")
                inner = am["codecs"][0]["configuration"]["chunk_shape"]
                shard = am["chunk_grid"]["configuration"]["chunk_shape"]
                self.assertEqual(inner[-3:], [e, e, e])
                per_shard = 1
                for s, c in zip(shard, inner):
                    per_shard *= s // c
                shards = 1
                for n, s in zip(am["shape"], shard):
                    shards *= -(-n // s)
                files = [f for f in glob.glob(os.path.join(ex.root, path, str(level), "c", "**"),
                                              recursive=True) if os.path.isfile(f)]
                self.assertLessEqual(len(files), shards, f"{path}/{level}: a file per shard")
                for f in files:
                    with open(f, "rb") as fh:
                        data = fh.read()
                    index = data[-(16 * per_shard + 4):-4]
                    (crc,) = struct.unpack("<I", data[-4:])
                    self.assertEqual(crc, crc32c(index), f"{f}: shard index crc32c")

    # ---- cases ----

    def test_dims_not_multiples_of_the_brick_edge(self):
        vpk = self.make("odd", "--dims", "40,30,20", "--edge", "16")
        ex, checked = self.check_volume(vpk, "odd")
        self.assertEqual(checked, 4 * len(self.info(vpk)["levels"]))
        # Some bricks equal the fill value (gel, air, unlabelled): not written.
        level0 = os.path.join(ex.root, "ct", "0")
        self.assertGreater(len(os.listdir(level0)), 0)

    def test_one_brick(self):
        vpk = self.make("one", "--dims", "10,12,9", "--edge", "16")
        self.assertEqual(len(self.info(vpk)["levels"]), 1)
        self.check_volume(vpk, "one")

    def test_uint16_labels_725(self):
        vpk = self.make("many", "--dims", "48,40,24", "--edge", "16", "--labels", "725")
        meta = self.info(vpk)
        self.assertEqual(len(meta["label_table"]), 725)
        self.assertEqual([c["type"] for c in meta["channels"]], ["rgba8", "int16", "uint16"])
        self.check_volume(vpk, "many")

    def test_empty_label_table(self):
        vpk = self.make("empty", "--empty-label-table")
        self.assertEqual(self.info(vpk).get("label_table", []), [])
        self.check_volume(vpk, "empty")

    def test_raw_bricks(self):
        vpk = self.make("raw", "--raw")
        self.check_volume(vpk, "raw")

    def test_no_copy_gives_the_same_values(self):
        vpk = self.make("nocopy")
        self.check_volume(vpk, "nocopy", "--no-copy")

    def test_channel_and_level_subset(self):
        vpk = self.make("subset", "--dims", "70,40,33", "--edge", "16")
        self.check_volume(vpk, "subset-labels", "--channels", "ct,labels", "--levels", "1-2",
                          channels=("ct", "labels"), levels=[1, 2])
        self.check_volume(vpk, "subset-only-labels", "--channels", "labels", "--levels", "0",
                          channels=("labels",), levels=[0])

    def test_existing_output_is_kept_without_overwrite(self):
        vpk = self.make("exists")
        out = os.path.join(self.tmp, "exists.zarr")
        os.makedirs(out)
        marker = os.path.join(out, "keep")
        open(marker, "w").close()
        p = run([tool("vispack-export"), vpk, "--ome-zarr", out, "--quiet"], check=False)
        self.assertEqual(p.returncode, 2, p.stderr)
        self.assertEqual(len(p.stderr.strip().splitlines()), 1)
        self.assertIn("exists", p.stderr)
        self.assertTrue(os.path.exists(marker))
        run([tool("vispack-export"), vpk, "--ome-zarr", out, "--quiet", "--overwrite",
             "--ngff", NGFF])
        self.assertFalse(os.path.exists(marker))
        self.assertEqual(glob.glob(os.path.join(self.tmp, "exists.zarr.*")), [])


if __name__ == "__main__":
    unittest.main(verbosity=2)
