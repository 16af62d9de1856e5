#!/usr/bin/python3
"""Serves a vispack OME-Zarr export (vispack-export, docs/OME_ZARR.md) on 127.0.0.1 for
neuroglancer and other web viewers, and prints a neuroglancer link with its layers set up.

Usage: scripts/serve_ome_zarr.py OUT.zarr [--port 8000] [--viewer URL | --neuroglancer DIR]
                                 [--print-state]

The export's parent folder is served over HTTP with `Access-Control-Allow-Origin: *` (a viewer
page on another origin fetches the chunks), answers a missing chunk with 404 (the fill value) and
honours byte ranges (`Range: bytes=A-B`, `A-`, `-N`: a Zarr v3 reader fetches a shard's index,
then its chunks, as ranges of the shard file; NGFF 0.5). --port 0 takes a free port; the first
line printed names the address. The printed link opens neuroglancer (default
https://neuroglancer-demo.appspot.com, or --viewer URL, or --neuroglancer DIR: a neuroglancer
build, e.g. tests/js/neuroglancer made by scripts/fetch-js-deps.sh, served here at /neuroglancer/)
with the view on the volume's centre and layers:
  colour  the rgb image, its c axis made a channel dimension (c^) and drawn as RGB
  ct      the CT image (hidden), window 400 HU at 40 HU
  labels  each label image as a segmentation layer, every segment shown, its panel open on the
          segment list; segment names and colours from a neuroglancer "segment properties"
          source this server makes from the image-label metadata (at
          URL/.../labels/NAME/neuroglancer_segment_properties/info)
--print-state prints the state JSON and exits without serving. Standard library only.
"""
import argparse
import http.server
import json
import os
import re
import shutil
import sys
import urllib.parse

SEGMENT_PROPERTIES = "neuroglancer_segment_properties"
VIEWER_PATH = "/neuroglancer/"
FIT_PIXELS = 300  # the cross-sections' zoom fits the volume's largest side in this many pixels


def read_json(path):
    with open(path) as fh:
        return json.load(fh)


def read_attrs(group):
    """A group's OME attributes (0.4 .zattrs, or 0.5 zarr.json's attributes.ome)."""
    if os.path.exists(os.path.join(group, ".zattrs")):
        return read_json(os.path.join(group, ".zattrs"))
    attrs = read_json(os.path.join(group, "zarr.json")).get("attributes", {})
    return attrs.get("ome", attrs)


def array_shape(array):
    """An array's shape from its .zarray (Zarr v2) or zarr.json (v3)."""
    meta = os.path.join(array, ".zarray")
    return read_json(meta if os.path.exists(meta) else os.path.join(array, "zarr.json"))["shape"]


def segment_properties(label_group):
    """neuroglancer's segment properties (names; colours go in the layer) from an image-label."""
    il = read_attrs(label_group).get("image-label", {})
    props = il.get("properties", [])
    return {"@type": SEGMENT_PROPERTIES,
            "inline": {"ids": [str(p["label-value"]) for p in props],
                       "properties": [{"id": "name", "type": "label",
                                       "values": [p.get("name", "") for p in props]}]}}


def image_layer(export, im, url, space):
    """The neuroglancer layer of one exported image (vispack's root attributes name its kind):
    colour as RGB; a scalar image (CT, alpha) hidden, grey through its omero window."""
    if im["kind"] == "colour":
        return {"type": "image", "name": "colour",
                "source": {"url": url, "transform": {"outputDimensions": {"c^": [1, ""], **space}}},
                "shader": "#uicontrol invlerp red(range=[0, 255], channel=[0])\n"
                          "#uicontrol invlerp green(range=[0, 255], channel=[1])\n"
                          "#uicontrol invlerp blue(range=[0, 255], channel=[2])\n"
                          "void main() { emitRGB(vec3(red(), green(), blue())); }"}
    window = read_attrs(os.path.join(export, im["path"])).get("omero", {}).get(
        "channels", [{}])[0].get("window", {})
    low, high = window.get("start", 0), window.get("end", 255)
    return {"type": "image", "name": im["path"], "source": url, "visible": False,
            "shader": f"#uicontrol invlerp normalized(range=[{low:g}, {high:g}])\n"
                      "void main() { emitGrayscale(normalized()); }"}


def label_layer(export, im, url, base_url):
    """A segmentation layer: every segment shown in its image-label colour, names attached."""
    attrs = read_attrs(os.path.join(export, im["path"]))
    colours = {str(c["label-value"]): "#%02x%02x%02x" % tuple(c["rgba"][:3])
               for c in attrs.get("image-label", {}).get("colors", []) if c["label-value"] != 0}
    return {"type": "segmentation", "name": im["path"].split("/")[-1],
            "source": [url, f"precomputed://{base_url}/{im['path']}/{SEGMENT_PROPERTIES}"],
            "segments": sorted(colours, key=int), "segmentColors": colours,
            "selectedAlpha": 0.35, "tab": "segments"}


def state(export, base_url):
    """The neuroglancer state for the export at base_url (the served URL of OUT.zarr).

    Global dimensions x, y, z (x across the screen in the xy view) in metres, the view on the
    middle voxel of level 0 (NGFF puts voxel i's centre at translation + i * scale, and so does
    neuroglancer: position i shows voxel i alone, i + 0.5 lies between two), cross-sections
    zoomed to fit."""
    root_meta = ".zattrs" if os.path.exists(os.path.join(export, ".zattrs")) else "zarr.json"
    root = read_json(os.path.join(export, root_meta))
    images = root.get("attributes", root)["vispack"]["images"]
    scheme = "zarr2" if root.get("attributes") is None else "zarr3"
    layers, space, position, extent_mm = [], {}, [], 0.0
    for im in images:
        url = f"{scheme}://{base_url}/{im['path']}/"
        group = os.path.join(export, im["path"])
        if not space:  # the first image's level 0 sets the global dimensions and the view
            dataset = read_attrs(group)["multiscales"][0]["datasets"][0]
            scale_zyx = dataset["coordinateTransformations"][0]["scale"][-3:]
            shape_zyx = array_shape(os.path.join(group, dataset["path"]))[-3:]
            space = {n: [scale_zyx[i] * 1e-3, "m"] for n, i in (("x", 2), ("y", 1), ("z", 0))}
            position = [shape_zyx[i] // 2 for i in (2, 1, 0)]
            extent_mm = max(n * s for n, s in zip(shape_zyx, scale_zyx))
            finest_mm = min(scale_zyx)
        if im["kind"] == "labels":
            layers.append(label_layer(export, im, url, base_url))
        else:
            layers.append(image_layer(export, im, url, {n: space[n] for n in "zyx"}))
    view = {}
    if space:
        # Zoom in neuroglancer's units: its canonical voxel is the finest dimension's spacing.
        view = {"dimensions": space, "position": position,
                "crossSectionScale": extent_mm / finest_mm / FIT_PIXELS,
                "projectionScale": 2 * extent_mm / finest_mm}
    return {**view, "layers": layers, "layout": "4panel",
            "selectedLayer": {"layer": layers[-1]["name"], "visible": True} if layers else {}}


def parse_range(header, size):
    """(start, end) inclusive of a single `bytes=` range against a file of size bytes, None when
    the header asks for something else (served whole), or ValueError when it cannot be met."""
    m = re.fullmatch(r"\s*bytes\s*=\s*(\d*)\s*-\s*(\d*)\s*", header or "")
    if not m or (m.group(1) == "" and m.group(2) == ""):
        return None
    if m.group(1) == "":  # suffix: the last N bytes
        n = int(m.group(2))
        if n == 0:
            raise ValueError("empty suffix range")
        return max(0, size - n), size - 1
    start = int(m.group(1))
    end = min(int(m.group(2)), size - 1) if m.group(2) else size - 1
    if start >= size or end < start:
        raise ValueError(f"range {start}-{end} outside a file of {size} bytes")
    return start, end


def make_handler(folder, viewer_dir):
    """The request handler: folder at /, viewer_dir (if any) at VIEWER_PATH."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *a, **kw):
            super().__init__(*a, directory=folder, **kw)

        def translate_path(self, path):
            if viewer_dir and urllib.parse.urlparse(path).path.startswith(VIEWER_PATH):
                saved, self.directory = self.directory, viewer_dir
                try:
                    return super().translate_path(path[len(VIEWER_PATH) - 1:])
                finally:
                    self.directory = saved
            return super().translate_path(path)

        def end_headers(self):
            self.send_header("Access-Control-Allow-Origin", "*")
            self.send_header("Access-Control-Expose-Headers", "Content-Range, Content-Length")
            super().end_headers()

        def do_GET(self):
            path = urllib.parse.unquote(urllib.parse.urlparse(self.path).path)
            marker = f"/{SEGMENT_PROPERTIES}/info"
            if path.endswith(marker):
                group = os.path.join(folder, path[1:-len(marker)])
                self.send_bytes(200, json.dumps(segment_properties(group)).encode(),
                                "application/json")
                return
            file_path = self.translate_path(self.path)
            if "Range" in self.headers and os.path.isfile(file_path):
                self.send_range(file_path)
                return
            super().do_GET()

        def send_bytes(self, code, body, content_type, extra=()):
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            for k, v in extra:
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(body)

        def send_range(self, file_path):
            size = os.path.getsize(file_path)
            try:
                span = parse_range(self.headers["Range"], size)
            except ValueError as err:
                self.send_bytes(416, str(err).encode(), "text/plain",
                                [("Content-Range", f"bytes */{size}")])
                return
            if span is None:
                super().do_GET()
                return
            start, end = span
            with open(file_path, "rb") as fh:
                fh.seek(start)
                body = fh.read(end - start + 1)
            self.send_bytes(206, body, self.guess_type(file_path),
                            [("Content-Range", f"bytes {start}-{end}/{size}"),
                             ("Accept-Ranges", "bytes")])

        def copyfile(self, source, outputfile):
            try:
                shutil.copyfileobj(source, outputfile)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the viewer cancelled the request (a chunk no longer in view)

        def log_message(self, *args):
            pass

    return Handler


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", help="an OME-Zarr folder written by vispack-export")
    ap.add_argument("--port", type=int, default=8000, help="0: a free port (printed)")
    ap.add_argument("--viewer", default="https://neuroglancer-demo.appspot.com/")
    ap.add_argument("--neuroglancer", metavar="DIR",
                    help=f"a neuroglancer build (index.html) to serve at {VIEWER_PATH} and link to")
    ap.add_argument("--print-state", action="store_true", help="print the state JSON and exit")
    args = ap.parse_args()
    export = os.path.abspath(args.export.rstrip("/"))
    root_meta = [f for f in (".zattrs", "zarr.json") if os.path.exists(os.path.join(export, f))]
    if not root_meta or "vispack" not in json.dumps(read_json(os.path.join(export, root_meta[0]))):
        print(f"serve_ome_zarr: {export}: not an OME-Zarr export of vispack-export",
              file=sys.stderr)
        return 2
    viewer_dir = os.path.abspath(args.neuroglancer) if args.neuroglancer else None
    if viewer_dir and not os.path.isfile(os.path.join(viewer_dir, "index.html")):
        print(f"serve_ome_zarr: {viewer_dir}: no index.html (scripts/fetch-js-deps.sh builds one)",
              file=sys.stderr)
        return 2
    if args.print_state:
        base = f"http://127.0.0.1:{args.port}/{os.path.basename(export)}"
        print(json.dumps(state(export, base), indent=1))
        return 0
    folder = os.path.dirname(export) or "."
    server = http.server.ThreadingHTTPServer(("127.0.0.1", args.port),
                                             make_handler(folder, viewer_dir))
    port = server.server_address[1]
    base = f"http://127.0.0.1:{port}/{os.path.basename(export)}"
    viewer = f"http://127.0.0.1:{port}{VIEWER_PATH}" if viewer_dir else args.viewer
    st = json.dumps(state(export, base), separators=(",", ":"))
    link = viewer.rstrip("/") + "/#!" + urllib.parse.quote(st)
    print(f"serving {export} at {base}/ (Ctrl-C stops)\nneuroglancer: {link}", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
