#!/usr/bin/python3
"""Serves a vispack OME-Zarr export (vispack-export, docs/OME_ZARR.md) on 127.0.0.1 for
neuroglancer and other web viewers, and prints a neuroglancer link with its layers set up.

Usage: scripts/serve_ome_zarr.py OUT.zarr [--port 8000] [--viewer URL] [--print-state]

The export's parent folder is served over HTTP with `Access-Control-Allow-Origin: *` (a viewer
page on another origin fetches the chunks) and answers a missing chunk with 404 (the fill value).
The printed link opens neuroglancer (default https://neuroglancer-demo.appspot.com, or --viewer,
e.g. a neuroglancer built from npm and served locally) with layers:
  colour  the rgb image, its c axis made a channel dimension (c^) and drawn as RGB
  ct      the CT image, window 400 HU at 40 HU
  labels  each label image as a segmentation layer; segment names and colours from a
          neuroglancer "segment properties" source this server makes from the image-label
          metadata (at URL/.../labels/NAME/neuroglancer_segment_properties/info)
--print-state prints the state JSON and exits without serving. Standard library only.
"""
import argparse
import http.server
import json
import os
import sys
import urllib.parse

SEGMENT_PROPERTIES = "neuroglancer_segment_properties"


def read_attrs(group):
    """A group's OME attributes (0.4 .zattrs, or 0.5 zarr.json's attributes.ome)."""
    if os.path.exists(os.path.join(group, ".zattrs")):
        with open(os.path.join(group, ".zattrs")) as fh:
            return json.load(fh)
    with open(os.path.join(group, "zarr.json")) as fh:
        attrs = json.load(fh).get("attributes", {})
    return attrs.get("ome", attrs)


def segment_properties(label_group):
    """neuroglancer's segment properties (names; colours go in the layer) from an image-label."""
    il = read_attrs(label_group).get("image-label", {})
    props = il.get("properties", [])
    return {"@type": SEGMENT_PROPERTIES,
            "inline": {"ids": [str(p["label-value"]) for p in props],
                       "properties": [{"id": "name", "type": "label",
                                       "values": [p.get("name", "") for p in props]}]}}


def state(export, base_url):
    """The neuroglancer state for the export at base_url (the served URL of OUT.zarr)."""
    with open(os.path.join(export, ".zattrs" if os.path.exists(os.path.join(export, ".zattrs"))
                           else "zarr.json")) as fh:
        root = json.load(fh)
    images = root.get("attributes", root)["vispack"]["images"]
    scheme = "zarr2" if root.get("attributes") is None else "zarr3"
    layers = []
    for im in images:
        url = f"{scheme}://{base_url}/{im['path']}/"
        ms = read_attrs(os.path.join(export, im["path"]))["multiscales"][0]
        scale = ms["datasets"][0]["coordinateTransformations"][0]["scale"][-3:]
        space = {n: [s * 1e-3, "m"] for n, s in zip("zyx", scale)}
        if im["kind"] == "colour":
            layers.append({
                "type": "image", "name": "colour",
                "source": {"url": url, "transform": {"outputDimensions":
                                                     {"c^": [1, ""], **space}}},
                "shader": "#uicontrol invlerp red(range=[0, 255], channel=[0])\n"
                          "#uicontrol invlerp green(range=[0, 255], channel=[1])\n"
                          "#uicontrol invlerp blue(range=[0, 255], channel=[2])\n"
                          "void main() { emitRGB(vec3(red(), green(), blue())); }"})
        elif im["kind"] == "scalar":
            layers.append({"type": "image", "name": im["path"], "source": url, "visible": False,
                           "shader": "#uicontrol invlerp normalized(range=[-160, 240])\n"
                                     "void main() { emitGrayscale(normalized()); }"})
        elif im["kind"] == "labels":
            attrs = read_attrs(os.path.join(export, im["path"]))
            colours = {str(c["label-value"]): "#%02x%02x%02x" % tuple(c["rgba"][:3])
                       for c in attrs.get("image-label", {}).get("colors", [])
                       if c["label-value"] != 0}
            layers.append({"type": "segmentation", "name": im["path"].split("/")[-1],
                           "source": [url, f"precomputed://{base_url}/{im['path']}/"
                                           f"{SEGMENT_PROPERTIES}"],
                           "segmentColors": colours, "selectedAlpha": 0.35})
    return {"layers": layers, "layout": "4panel",
            "selectedLayer": {"layer": layers[-1]["name"], "visible": True} if layers else {}}


def serve(export, port):
    folder = os.path.dirname(os.path.abspath(export)) or "."

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *a, **kw):
            super().__init__(*a, directory=folder, **kw)

        def end_headers(self):
            self.send_header("Access-Control-Allow-Origin", "*")
            super().end_headers()

        def do_GET(self):
            path = urllib.parse.unquote(urllib.parse.urlparse(self.path).path)
            marker = f"/{SEGMENT_PROPERTIES}/info"
            if path.endswith(marker):
                group = os.path.join(folder, path[1:-len(marker)])
                body = json.dumps(segment_properties(group)).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
                return
            super().do_GET()

        def log_message(self, *args):
            pass

    http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler).serve_forever()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", help="an OME-Zarr folder written by vispack-export")
    ap.add_argument("--port", type=int, default=8000)
    ap.add_argument("--viewer", default="https://neuroglancer-demo.appspot.com/")
    ap.add_argument("--print-state", action="store_true", help="print the state JSON and exit")
    args = ap.parse_args()
    export = os.path.abspath(args.export.rstrip("/"))
    base = f"http://127.0.0.1:{args.port}/{os.path.basename(export)}"
    st = state(export, base)
    if args.print_state:
        print(json.dumps(st, indent=1))
        return 0
    link = args.viewer.rstrip("/") + "/#!" + urllib.parse.quote(json.dumps(st, separators=(",", ":")))
    print(f"serving {export} at {base}/ (Ctrl-C stops)\nneuroglancer: {link}", flush=True)
    try:
        serve(export, args.port)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
