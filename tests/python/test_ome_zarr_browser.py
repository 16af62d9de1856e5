#!/usr/bin/python3
"""vispack-export's OME-Zarr opened in neuroglancer, in headless Chromium with software WebGL.

Run by ctest (tests/python/CMakeLists.txt, label browser) as
    /usr/bin/python3 tests/python/test_ome_zarr_browser.py 0.4|0.5
with VISPACK_BIN_DIR (vispack-phantom, vispack-run, vispack-export) set. The phantom `tiny` (a
body of 96 x 64 x 24 voxels, 9 named tissues) is packed and exported; scripts/serve_ome_zarr.py
serves the export and the neuroglancer bundle (tests/js/neuroglancer, scripts/fetch-js-deps.sh) on
127.0.0.1 and prints its link; tests/js/neuroglancer_views.mjs opens that link and variants of it
in Debian's chromium (SwiftShader WebGL 2) and saves screenshots and the page's text once
neuroglancer says every visible chunk is drawn. Checked against the packed volume read by
vispack's Python reader (python/vispack), at the middle slice, 4 screen pixels per voxel:
  - the colour layer: the volume's rectangle has the size the NGFF scales give and sits where
    the view's position puts it; each voxel's colour equals the data's, the body's pixel
    fraction and mean colour equal the data's;
  - level 1 (the layer made to draw its coarser level): lies exactly over level 0 (NGFF
    translation: half a coarse voxel minus half a fine one), its voxels equal level 1's data;
  - the labels layer: each voxel in its label table colour, as the labels data says;
  - the link as printed: the labels layer lists every label table name beside its id.
Exits 77 (ctest: skipped; under CI a failure, scripts/test.sh) when chromium, node, the npm
packages or the neuroglancer bundle are missing. VISPACK_KEEP_TEST_DIRS=1 keeps the screenshots.
"""
import copy
import json
import os
import shutil
import subprocess
import sys
import tempfile
import unittest
import urllib.parse

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE_DIR = os.path.normpath(os.path.join(HERE, "..", ".."))
NGFF = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] in ("0.4", "0.5") else "0.4"
if len(sys.argv) > 1 and sys.argv[1] in ("0.4", "0.5"):
    del sys.argv[1]
JS_DIR = os.path.join(SOURCE_DIR, "tests", "js")
VIEWS_SCRIPT = os.path.join(JS_DIR, "neuroglancer_views.mjs")
NEUROGLANCER = os.path.join(JS_DIR, "neuroglancer")
SERVER = os.path.join(SOURCE_DIR, "scripts", "serve_ome_zarr.py")
CHROMIUM = os.environ.get("VISPACK_CHROMIUM", "/usr/bin/chromium")
sys.path.insert(0, os.path.join(SOURCE_DIR, "python"))

try:
    import numpy as np
    from PIL import Image
    import vispack
except ImportError as err:  # pragma: no cover - depends on the machine
    print(f"test_ome_zarr_browser: skipped: {err} (install python3-numpy python3-pil "
          "python3-zstandard)")
    sys.exit(77)
_missing = [what for what, ok in (
    ("chromium (apt chromium)", os.access(CHROMIUM, os.X_OK)),
    ("node", shutil.which("node") is not None),
    ("puppeteer-core (scripts/fetch-js-deps.sh)",
     os.path.isdir(os.path.join(JS_DIR, "node_modules", "puppeteer-core"))),
    ("the neuroglancer bundle (scripts/fetch-js-deps.sh)",
     os.path.isfile(os.path.join(NEUROGLANCER, "index.html")))) if not ok]
if _missing:
    print(f"test_ome_zarr_browser: skipped: missing {', '.join(_missing)}")
    sys.exit(77)

PX = 4  # screen pixels per voxel along x in the measured views
BACKGROUND = (255, 0, 255)  # the cross-sections' background: no voxel of the body has it
MATCH = 0.995  # fraction of voxels that must match (software rasterisation rounds, never more)


def run(args, **kw):
    p = subprocess.run(args, capture_output=True, text=True, **kw)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} exited {p.returncode}: {p.stderr[-2000:]}")
    return p


def tool(name):
    return os.path.join(os.environ.get("VISPACK_BIN_DIR", os.path.join(SOURCE_DIR, "build", "bin")),
                        name)


def make_export(folder):
    """The tiny phantom packed (no OpenVDB) and exported; returns (vpk path, export path)."""
    run([tool("vispack-phantom"), "--out", folder, "--preset", "tiny", "--quiet"])
    config_path = os.path.join(folder, "config.json")
    with open(config_path) as fh:
        config = json.load(fh)
    vpk = os.path.join(folder, "body.vpk")
    config.update(output=vpk, vdb={**config.get("vdb", {}), "enabled": False})
    with open(config_path, "w") as fh:
        json.dump(config, fh)
    run([tool("vispack-run"), config_path, "--quiet"])
    export = os.path.join(folder, "body.zarr")
    run([tool("vispack-export"), vpk, "--ome-zarr", export, "--ngff", NGFF, "--quiet"])
    return vpk, export


def link_state(link):
    """The neuroglancer state in a link's fragment (#!JSON)."""
    return json.loads(urllib.parse.unquote(link.split("#!", 1)[1]))


def level_one_render_scale(spacing):
    """The image layer's crossSectionRenderScale that makes neuroglancer draw level 1 at PX pixels
    per level-0 voxel: it takes the coarsest level none of whose voxel sides exceeds
    1.1 * pixel size * this scale (sliceview/base.js filterVisibleSources), so the limit lies
    halfway between level 1's longest side and level 2's."""
    pixel_mm = spacing[0] / PX * 1.1
    return 1.5 * 2 * max(spacing) / pixel_mm


def state_link(viewer, st):
    return viewer + "#!" + urllib.parse.quote(json.dumps(st, separators=(",", ":")))


def run_through(inside, start):
    """(first, last) index of the run of true values in a 1-D mask that holds start."""
    assert inside[start], "the panel's centre is not inside the volume"
    first, last = start, start
    while first > 0 and inside[first - 1]:
        first -= 1
    while last + 1 < len(inside) and inside[last + 1]:
        last += 1
    return first, last


def volume_rectangle(panel):
    """(x0, y0, x1, y1), inclusive, of the volume's slice in a panel: the run of non-background
    pixels through the panel's centre along its row and its column (the panel's overlays, the
    axis legend and buttons in its corners, are not in it)."""
    inside = np.any(panel != BACKGROUND, axis=-1)
    cy, cx = panel.shape[0] // 2, panel.shape[1] // 2
    x0, x1 = run_through(inside[cy], cx)
    y0, y1 = run_through(inside[:, cx], cy)
    return x0, y0, x1, y1


class BrowserTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="vispack-browser-")
        cls.vpk, export = make_export(cls.tmp)
        cls.server = subprocess.Popen(
            [sys.executable, SERVER, export, "--port", "0", "--neuroglancer", NEUROGLANCER],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first, second = cls.server.stdout.readline(), cls.server.stdout.readline()
        if not second.startswith("neuroglancer: "):
            cls.server.kill()
            raise RuntimeError(f"serve_ome_zarr.py: {first}{second}{cls.server.stderr.read()}")
        cls.link = second.split(" ", 1)[1].strip()
        viewer = cls.link.split("#!", 1)[0]
        volume = vispack.open(cls.vpk)
        cls.volume = volume
        nz, ny, nx = volume["rgba"].level(0).shape[:3]
        cls.slice = nz // 2  # NGFF: voxel k's centre is at k, so position k shows slice k alone
        spacing = volume.spacing_mm  # x, y, z
        cls.px = (PX, PX * spacing[1] / spacing[0])  # screen pixels per voxel in x and y
        user = link_state(cls.link)
        views = {"user": user,
                 "colour": cls.measured_view(user, nx, ny, spacing, "colour", {}),
                 "level1": cls.measured_view(user, nx, ny, spacing, "colour",
                                             {"crossSectionRenderScale":
                                              level_one_render_scale(spacing)}),
                 "labels": cls.measured_view(user, nx, ny, spacing, "labels",
                                             {"selectedAlpha": 1})}
        cls.names = list(views)
        out = os.path.join(cls.tmp, "views")
        cls.views_run = subprocess.run(
            ["node", VIEWS_SCRIPT, out, *(state_link(viewer, v) for v in views.values())],
            capture_output=True, text=True, timeout=300)
        cls.shots, cls.records = {}, {}
        for i, name in enumerate(cls.names):
            cls.shots[name] = np.asarray(Image.open(os.path.join(out, f"view-{i}.png"))
                                         .convert("RGB")).astype(int)
            with open(os.path.join(out, f"view-{i}.json")) as fh:
                cls.records[name] = json.load(fh)

    @classmethod
    def measured_view(cls, user, nx, ny, spacing, shown, layer_options):
        """The printed state made measurable: one xy panel at PX pixels per voxel on the volume's
        centre and slice, one layer shown, no axis lines, scale bar, bounding box or side panel,
        a background no voxel has."""
        st = copy.deepcopy(user)
        finest = min(spacing)
        # A quarter pixel off the volume's centre: a panel of odd size has a pixel centre at its
        # middle, and voxel edges there would be sampled on the edge (either voxel is right).
        st.update(layout="xy", position=[(nx - 1) / 2 + 0.25 / cls.px[0],
                                         (ny - 1) / 2 + 0.25 / cls.px[1], cls.slice],
                  crossSectionScale=finest / (PX * spacing[0]), showAxisLines=False,
                  showScaleBar=False, showDefaultAnnotations=False,
                  crossSectionBackgroundColor="#%02x%02x%02x" % BACKGROUND,
                  selectedLayer={"visible": False})
        for layer in st["layers"]:
            layer["visible"] = layer["name"] == shown
            if layer["visible"]:
                layer.update(layer_options)
        return st

    @classmethod
    def tearDownClass(cls):
        cls.server.terminate()
        cls.server.wait(timeout=10)
        if not os.environ.get("VISPACK_KEEP_TEST_DIRS"):
            shutil.rmtree(cls.tmp, ignore_errors=True)
        else:
            print(f"kept {cls.tmp}", file=sys.stderr)

    def panel(self, name):
        """The screenshot of a measured view cut to its data panel."""
        (rect,) = self.records[name]["panels"]
        x, y = int(round(rect["x"])), int(round(rect["y"]))
        return self.shots[name][y:y + int(rect["height"]), x:x + int(rect["width"])]

    def volume_box(self, name):
        return volume_rectangle(self.panel(name))

    def voxel_centres(self, name, level=0):
        """The panel's pixels at the centre of each voxel of the level (y, x, rgb), the level's
        voxels laid from the level-0 volume's top-left corner."""
        x0, y0, _, _ = self.volume_box("colour")
        f = 2 ** level
        data_shape = self.volume["rgba"].level(level).shape
        ys = (y0 + (np.arange(data_shape[1]) + 0.5) * f * self.px[1]).astype(int)
        xs = (x0 + (np.arange(data_shape[2]) + 0.5) * f * self.px[0]).astype(int)
        return self.panel(name)[ys[:, None], xs[None, :]]

    def test_views_ready_on_software_webgl(self):
        self.assertEqual(self.views_run.returncode, 0, self.views_run.stderr + "\n" +
                         "\n".join(e for r in self.records.values() for e in r["errors"]))
        for name, record in self.records.items():
            self.assertIsNotNone(record["renderer"], f"{name}: no WebGL 2")
            self.assertEqual(record["errors"], [], name)
        print(f"WebGL renderer: {self.records['user']['renderer']}; ready after "
              + ", ".join(f"{n} {r['ready_ms']} ms" for n, r in self.records.items()),
              file=sys.stderr)

    def test_colour_layer_shows_the_body(self):
        x0, y0, x1, y1 = self.volume_box("colour")
        nz, ny, nx = self.volume["rgba"].level(0).shape[:3]
        self.assertAlmostEqual(x1 - x0 + 1, nx * self.px[0], delta=1)
        self.assertAlmostEqual(y1 - y0 + 1, ny * self.px[1], delta=1)
        h, w = self.panel("colour").shape[:2]
        self.assertAlmostEqual((x0 + x1 + 1) / 2, w / 2, delta=1.5)  # the view's centre
        self.assertAlmostEqual((y0 + y1 + 1) / 2, h / 2, delta=1.5)
        shown = self.voxel_centres("colour")
        want = self.volume["rgba"].level(0)[self.slice][..., :3].astype(int)
        close = np.abs(shown - want).max(axis=-1) <= 2
        self.assertGreaterEqual(close.mean(), MATCH)
        body_shown, body_want = shown.any(axis=-1), want.any(axis=-1)
        self.assertGreater(body_want.mean(), 0.2)  # the slice holds a body
        self.assertAlmostEqual(body_shown.mean(), body_want.mean(), delta=0.005)
        mean_shown, mean_want = shown[body_want].mean(axis=0), want[body_want].mean(axis=0)
        np.testing.assert_allclose(mean_shown, mean_want, atol=1.0)
        print(f"colour: {close.mean():.4f} of voxels within 2; body {body_shown.mean():.4f} of "
              f"the slice shown, {body_want.mean():.4f} in the data; mean rgb shown "
              f"{np.round(mean_shown, 2)}, data {np.round(mean_want, 2)}", file=sys.stderr)

    def test_level_one_lies_over_level_zero(self):
        self.assertEqual(self.volume_box("level1"), self.volume_box("colour"))
        shown = self.voxel_centres("level1", level=1)
        # Level-1 slice k covers level-0 coordinates [2k - 0.5, 2k + 1.5).
        k = (self.slice * 2 + 1) // 4
        want = self.volume["rgba"].level(1)[k][..., :3].astype(int)
        close = np.abs(shown - want).max(axis=-1) <= 2
        self.assertGreaterEqual(close.mean(), MATCH)
        # Every pixel, not only the voxel centres: a shift of the coarse grid shows at its edges.
        x0, y0, x1, y1 = self.volume_box("level1")
        pixels = self.panel("level1")[y0:y1 + 1, x0:x1 + 1]
        rep = (int(2 * self.px[1]), int(2 * self.px[0]))
        upsampled = np.repeat(np.repeat(want, rep[0], axis=0), rep[1], axis=1)
        same = np.abs(pixels - upsampled[:pixels.shape[0], :pixels.shape[1]]).max(axis=-1) <= 2
        self.assertGreaterEqual(same.mean(), MATCH)
        print(f"level 1: {close.mean():.4f} of voxels, {same.mean():.4f} of pixels as the data",
              file=sys.stderr)

    def test_labels_layer_draws_the_label_table_colours(self):
        table = self.volume.metadata["label_table"]
        colours = np.array([BACKGROUND] + [t["colour"] for t in table])
        ids = np.array([0] + [t["id"] for t in table])
        shown = self.voxel_centres("labels")
        distance = np.abs(shown[..., None, :] - colours[None, None]).max(axis=-1)
        seen = np.where(distance.min(axis=-1) <= 2, ids[distance.argmin(axis=-1)], -1)
        want = self.volume["labels"].level(0)[self.slice].astype(int)
        self.assertGreaterEqual((seen == want).mean(), MATCH)
        self.assertGreater(len(np.unique(want)), 5)  # the slice cuts most tissues
        print(f"labels: {(seen == want).mean():.4f} of voxels in their label's colour, "
              f"{len(np.unique(want)) - 1} labels in the slice", file=sys.stderr)

    def test_printed_link_lists_the_segment_names(self):
        text = self.records["user"]["text"]
        for entry in self.volume.metadata["label_table"]:
            self.assertIn(f"{entry['id']}\n{entry['name']}\n", text + "\n")


if __name__ == "__main__":
    unittest.main(verbosity=2)
