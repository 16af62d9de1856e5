#!/usr/bin/python3
"""scripts/serve_ome_zarr.py over HTTP, without a browser: byte ranges (a Zarr v3 reader reads a
shard's index and chunks as ranges), CORS, missing chunks, the segment-properties source made
from image-label, the neuroglancer bundle's folder, the printed link's state, bad input.

Run by ctest (tests/python/CMakeLists.txt, label python) as
    /usr/bin/python3 tests/python/test_serve_ome_zarr.py
with VISPACK_BIN_DIR (vispack-export) and VISPACK_MAKE_SAMPLE (format_make_sample) set. The
server is the script itself, started on a free port; expected bytes are read from the files.
"""
import json
import os
import shutil
import subprocess
import sys
import tempfile
import unittest
import urllib.error
import urllib.parse
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE_DIR = os.path.normpath(os.path.join(HERE, "..", ".."))
SERVER = os.path.join(SOURCE_DIR, "scripts", "serve_ome_zarr.py")
BIN_DIR = os.environ.get("VISPACK_BIN_DIR", os.path.join(SOURCE_DIR, "build", "bin"))
SHARD = "rgb/0/c/0/0/0/0"  # the first shard of the colour's level 0 (NGFF 0.5)


def get(url, headers=None):
    """(status, headers, body) of a GET, error statuses included."""
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.headers, response.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers, err.read()


class ServeTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="vispack-serve-")
        sample = os.environ.get("VISPACK_MAKE_SAMPLE", "")
        if not os.path.exists(sample):
            raise unittest.SkipTest("VISPACK_MAKE_SAMPLE (format_make_sample) is not set")
        vpk = os.path.join(cls.tmp, "s.vpk")
        subprocess.run([sample, vpk, "--dims", "40,30,20", "--edge", "16", "--labels", "5"],
                       check=True, capture_output=True)
        cls.export = os.path.join(cls.tmp, "body.zarr")
        subprocess.run([os.path.join(BIN_DIR, "vispack-export"), vpk, "--ome-zarr", cls.export,
                        "--ngff", "0.5", "--quiet"], check=True, capture_output=True)
        cls.viewer = os.path.join(cls.tmp, "viewer")
        os.mkdir(cls.viewer)
        with open(os.path.join(cls.viewer, "index.html"), "w") as fh:
            fh.write("<!-- a viewer -->")
        cls.server = subprocess.Popen(
            [sys.executable, SERVER, cls.export, "--port", "0", "--neuroglancer", cls.viewer],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first, second = cls.server.stdout.readline(), cls.server.stdout.readline()
        if not second.startswith("neuroglancer: "):
            cls.server.kill()
            raise RuntimeError(f"serve_ome_zarr.py: {first}{second}{cls.server.stderr.read()}")
        cls.base = first.split(" at ", 1)[1].split()[0].rstrip("/")  # http://127.0.0.1:P/body.zarr
        cls.link = second.split(" ", 1)[1].strip()
        with open(os.path.join(cls.export, SHARD), "rb") as fh:
            cls.shard = fh.read()

    @classmethod
    def tearDownClass(cls):
        cls.server.terminate()
        cls.server.wait(timeout=10)
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def ranged(self, spec):
        return get(f"{self.base}/{SHARD}", {"Range": spec})

    def test_byte_ranges(self):
        size = len(self.shard)
        self.assertGreater(size, 100)
        for spec, first, last in (("bytes=0-9", 0, 9), ("bytes=5-", 5, size - 1),
                                  ("bytes=-8", size - 8, size - 1),
                                  (f"bytes={size - 3}-{size + 50}", size - 3, size - 1),
                                  (f"bytes=-{size + 10}", 0, size - 1)):
            status, headers, body = self.ranged(spec)
            self.assertEqual(status, 206, spec)
            self.assertEqual(body, self.shard[first:last + 1], spec)
            self.assertEqual(headers["Content-Range"], f"bytes {first}-{last}/{size}", spec)
            self.assertEqual(int(headers["Content-Length"]), last - first + 1, spec)

    def test_unsatisfiable_and_unsupported_ranges(self):
        size = len(self.shard)
        for spec in (f"bytes={size}-", "bytes=9-3", "bytes=-0"):
            status, headers, _ = self.ranged(spec)
            self.assertEqual(status, 416, spec)
            self.assertEqual(headers["Content-Range"], f"bytes */{size}", spec)
        for spec in ("bytes=0-1,4-5", "items=0-3"):  # not a single byte range: the whole file
            status, _, body = self.ranged(spec)
            self.assertEqual((status, body), (200, self.shard), spec)

    def test_whole_files_missing_chunks_and_cors(self):
        status, headers, body = get(f"{self.base}/{SHARD}")
        self.assertEqual((status, body), (200, self.shard))
        self.assertEqual(headers["Access-Control-Allow-Origin"], "*")
        self.assertIn("Content-Range", headers["Access-Control-Expose-Headers"])
        status, headers, _ = get(f"{self.base}/rgb/0/c/0/9/9/9")
        self.assertEqual(status, 404)
        self.assertEqual(headers["Access-Control-Allow-Origin"], "*")

    def test_segment_properties_from_image_label(self):
        status, _, body = get(f"{self.base}/rgb/labels/labels/neuroglancer_segment_properties/info")
        self.assertEqual(status, 200)
        info = json.loads(body)
        with open(os.path.join(self.export, "rgb/labels/labels/zarr.json")) as fh:
            props = json.load(fh)["attributes"]["ome"]["image-label"]["properties"]
        self.assertEqual(len(props), 5)
        self.assertEqual(info["@type"], "neuroglancer_segment_properties")
        self.assertEqual(info["inline"]["ids"], [str(p["label-value"]) for p in props])
        (names,) = info["inline"]["properties"]
        self.assertEqual(names["values"], [p["name"] for p in props])

    def test_viewer_folder_and_link(self):
        port = urllib.parse.urlparse(self.base).port
        status, _, body = get(f"http://127.0.0.1:{port}/neuroglancer/index.html")
        self.assertEqual((status, body), (200, b"<!-- a viewer -->"))
        self.assertTrue(self.link.startswith(f"http://127.0.0.1:{port}/neuroglancer/#!"))
        state = json.loads(urllib.parse.unquote(self.link.split("#!", 1)[1]))
        self.assertEqual([layer["name"] for layer in state["layers"]],
                         ["colour", "alpha", "ct", "labels"])
        self.assertEqual(state["position"], [20, 15, 10])  # the middle voxel, x, y, z
        colour, labels = state["layers"][0], state["layers"][3]
        self.assertEqual(colour["source"]["url"], f"zarr3://{self.base}/rgb/")
        self.assertEqual(labels["segments"], ["1", "2", "3", "4", "5"])
        self.assertEqual(labels["source"][1],
                         f"precomputed://{self.base}/rgb/labels/labels/"
                         "neuroglancer_segment_properties")

    def test_not_an_export(self):
        p = subprocess.run([sys.executable, SERVER, self.tmp, "--print-state"],
                           capture_output=True, text=True)
        self.assertEqual(p.returncode, 2)
        self.assertEqual(len(p.stderr.strip().splitlines()), 1, p.stderr)
        self.assertIn("not an OME-Zarr export", p.stderr)


if __name__ == "__main__":
    unittest.main(verbosity=2)
