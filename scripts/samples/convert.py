#!/usr/bin/python3
"""Converts real sample data, extracted from Debian packages, into vispack slice folders.

Usage (called by scripts/fetch-sample-data.sh; run with /usr/bin/python3 for numpy):
  convert.py head-ct       EXTRACTED_DEB_DIR OUT_DIR
  convert.py aal           EXTRACTED_DEB_DIR OUT_DIR
  convert.py visible-woman EXTRACTED_DEB_DIR OUT_DIR

EXTRACTED_DEB_DIR is a `dpkg -x` tree; the input files are found by name anywhere inside it.
OUT_DIR must not exist yet or be empty (the caller converts into a temporary folder and renames it).
The sample's config.json is installed by the shell script (from configs/samples/<name>.json).
Every output is deterministic (same input -> same bytes).
Layouts and conventions: docs/SAMPLES.md.
"""
import gzip
import io
import json
import os
import plistlib
import shutil
import struct
import sys
import tarfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import pngio  # noqa: E402


class ConvertError(Exception):
    pass


def find_file(root, name):
    """Absolute path of the single file called `name` under `root`."""
    hits = []
    for d, _, files in os.walk(root):
        if name in files:
            hits.append(os.path.join(d, name))
    if not hits:
        raise ConvertError("%s: no file named %s in the extracted package" % (root, name))
    return sorted(hits)[0]


def log(msg):
    print("  " + msg, flush=True)


# ---------------------------------------------------------------------------------------- NRRD
def write_nrrd(path, volume_zyx, spacing_mm, origin_mm=(0.0, 0.0, 0.0)):
    """Writes a scalar volume (numpy array indexed [z][y][x]) as a single-file gzip NRRD in the
    same header form as common's write_nrrd (vispack/common/nrrd.h)."""
    names = {np.dtype(np.uint8): "uint8", np.dtype(np.uint16): "uint16",
             np.dtype(np.int16): "int16", np.dtype(np.int32): "int32"}
    dtype = volume_zyx.dtype
    if dtype not in names:
        raise ConvertError("write_nrrd: unsupported dtype %s" % dtype)
    nz, ny, nx = volume_zyx.shape
    sx, sy, sz = spacing_mm
    header = ("NRRD0004\n# written by vispack scripts/samples/convert.py\n"
              "type: %s\ndimension: 3\nspace dimension: 3\nsizes: %d %d %d\n"
              "space directions: (%r,0,0) (0,%r,0) (0,0,%r)\nkinds: domain domain domain\n"
              "space units: \"mm\" \"mm\" \"mm\"\nspace origin: (%r,%r,%r)\n" %
              (names[dtype], nx, ny, nz, float(sx), float(sy), float(sz), *map(float, origin_mm)))
    if dtype.itemsize > 1:
        header += "endian: little\n"
    header += "encoding: gzip\n\n"
    data = np.ascontiguousarray(volume_zyx.astype(dtype.newbyteorder("<"))).tobytes()
    buf = io.BytesIO()
    with gzip.GzipFile(fileobj=buf, mode="wb", compresslevel=6, mtime=0) as g:
        g.write(data)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(buf.getvalue())
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------- head CT
def convert_head_ct(deb_dir, out_dir):
    inv3 = find_file(deb_dir, "Cranium.inv3")
    log("reading %s" % os.path.basename(inv3))
    with tarfile.open(inv3, "r:gz") as tar:
        members = {os.path.basename(m.name): m for m in tar.getmembers() if m.isfile()}
        if "main.plist" not in members:
            raise ConvertError("%s: no main.plist inside the project archive" % inv3)
        main = plistlib.loads(tar.extractfile(members["main.plist"]).read())
        matrix = main.get("matrix", {})
        shape = [int(v) for v in matrix.get("shape", [])]
        dtype = matrix.get("dtype")
        fname = matrix.get("filename")
        spacing = [float(v) for v in main.get("spacing", [])]
        if len(shape) != 3 or dtype != "int16" or fname not in members or len(spacing) != 3:
            raise ConvertError("%s: main.plist matrix is %r, spacing %r; expected a 3-D int16 "
                               "matrix file" % (inv3, matrix, spacing))
        raw = tar.extractfile(members[fname]).read()
    nz, ny, nx = shape
    if len(raw) != nz * ny * nx * 2:
        raise ConvertError("%s: %s holds %d bytes, plist shape %r needs %d" %
                           (inv3, fname, len(raw), shape, nz * ny * nx * 2))
    hu = np.frombuffer(raw, "<i2").reshape(nz, ny, nx)
    log("CT %dx%dx%d int16, HU %d..%d, spacing %.4f x %.4f x %.4f mm (modality %s)" %
        (nx, ny, nz, hu.min(), hu.max(), spacing[0], spacing[1], spacing[2],
         main.get("modality")))
    stored = np.clip(hu.astype(np.int32) + 1024, 0, 65535).astype(np.uint16)
    # A grey rendering of the same slices for the pipeline's colour input, window -400..1000 HU:
    # air and the foam pad under the head (about -650 HU) are black like a dark background, so
    # the outline of the non-background matches the CT body outline (skin at about -100 HU is
    # grey 55, brain 80, bone up to 255).
    grey = (np.clip((hu.astype(np.float64) + 400.0) / 1400.0, 0.0, 1.0) * 255.0 + 0.5)
    grey = grey.astype(np.uint8)
    os.makedirs(os.path.join(out_dir, "ct"))
    os.makedirs(os.path.join(out_dir, "rgb"))
    for z in range(nz):
        pngio.write_png(os.path.join(out_dir, "ct", "ct_%04d.png" % z), stored[z])
        pngio.write_png(os.path.join(out_dir, "rgb", "rgb_%04d.png" % z),
                        np.repeat(grey[z][:, :, None], 3, axis=2))
    info = {"source": "invesalius-examples: Cranium.inv3 (%s)" % main.get("name"),
            "width": nx, "height": ny, "slices": nz, "spacing_mm": spacing,
            "stored": "hu + 1024 (16-bit PNG)", "hu_min": int(hu.min()),
            "hu_max": int(hu.max())}
    with open(os.path.join(out_dir, "info.json"), "w") as f:
        json.dump(info, f, indent=2)
        f.write("\n")
    log("wrote %d CT slices (16-bit, stored = HU + 1024) and %d grey RGB slices" % (nz, nz))


# ----------------------------------------------------------------------------------------- AAL
_NIFTI_TYPES = {2: np.uint8, 4: np.int16, 8: np.int32, 16: np.float32, 64: np.float64,
                256: np.int8, 512: np.uint16, 768: np.uint32}


def read_nifti(path):
    """(volume indexed [k][j][i], pixdim (i, j, k)) of a single-file NIfTI-1 (.nii or .nii.gz)."""
    with (gzip.open(path, "rb") if path.endswith(".gz") else open(path, "rb")) as f:
        data = f.read()
    if len(data) < 352:
        raise ConvertError("%s: too short for a NIfTI-1 header" % path)
    endian = "<" if struct.unpack("<i", data[0:4])[0] == 348 else ">"
    if struct.unpack(endian + "i", data[0:4])[0] != 348 or data[344:347] != b"n+1":
        raise ConvertError("%s: not a single-file NIfTI-1 image" % path)
    dim = struct.unpack(endian + "8h", data[40:56])
    datatype = struct.unpack(endian + "h", data[70:72])[0]
    pixdim = struct.unpack(endian + "8f", data[76:108])
    vox_offset = int(struct.unpack(endian + "f", data[108:112])[0])
    slope, inter = struct.unpack(endian + "2f", data[112:120])
    if dim[0] < 3 or any(d != 1 for d in dim[4:dim[0] + 1]) or datatype not in _NIFTI_TYPES:
        raise ConvertError("%s: unsupported NIfTI (dim %r, datatype %d)" % (path, dim, datatype))
    ni, nj, nk = dim[1:4]
    dt = np.dtype(_NIFTI_TYPES[datatype]).newbyteorder(endian)
    count = ni * nj * nk
    if len(data) < vox_offset + count * dt.itemsize:
        raise ConvertError("%s: truncated voxel data" % path)
    vol = np.frombuffer(data, dt, count, vox_offset).reshape(nk, nj, ni)
    if slope not in (0.0, 1.0) or inter != 0.0:
        vol = vol.astype(np.float64) * (slope if slope else 1.0) + inter
    return vol, pixdim[1:4]


def read_aal_names(path):
    """[(index, name, atlas_id)] from aal.nii.txt ("<index> <name> <id>" per line)."""
    entries = []
    with open(path, encoding="latin-1") as f:
        for n, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            if len(parts) != 3:
                raise ConvertError("%s:%d: expected '<index> <name> <id>', got %r" %
                                   (path, n, line.strip()))
            entries.append((int(parts[0]), parts[1], int(parts[2])))
    return entries


def make_palette(count):
    """`count` RGB colours, deterministic, greedy max-min Euclidean distance over a 16-level RGB
    lattice, starting from black (which is reserved for the background and not returned).
    Returns (colours, min pairwise distance including black)."""
    levels = np.arange(16) * 17
    cand = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 3)
    cand = cand.astype(np.float64)
    dist = np.linalg.norm(cand, axis=1)  # distance to the nearest chosen colour (black)
    chosen = []
    for _ in range(count):
        i = int(np.argmax(dist))  # first maximum: deterministic
        chosen.append(cand[i])
        dist = np.minimum(dist, np.linalg.norm(cand - cand[i], axis=1))
    pts = np.vstack([np.zeros(3), np.array(chosen)])
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    d[np.arange(len(pts)), np.arange(len(pts))] = np.inf
    return [tuple(int(v) for v in c) for c in chosen], float(d.min())


def convert_aal(deb_dir, out_dir):
    atlas_path = find_file(deb_dir, "aal.nii.gz")
    names_path = find_file(deb_dir, "aal.nii.txt")
    t1_path = find_file(deb_dir, "ch2.nii.gz")
    log("reading %s, %s, %s" % tuple(os.path.basename(p) for p in
                                     (atlas_path, names_path, t1_path)))
    atlas, pix = read_nifti(atlas_path)
    t1, t1_pix = read_nifti(t1_path)
    if atlas.shape != t1.shape or tuple(pix) != tuple(t1_pix):
        raise ConvertError("%s grid %r/%r differs from %s %r/%r" %
                           (atlas_path, atlas.shape, pix, t1_path, t1.shape, t1_pix))
    entries = read_aal_names(names_path)
    index_to_id = {}
    for idx, name, atlas_id in entries:
        if idx in index_to_id or not 0 < atlas_id <= 65535:
            raise ConvertError("%s: duplicate index %d or ID %d out of 1..65535" %
                               (names_path, idx, atlas_id))
        index_to_id[idx] = atlas_id
    present = set(int(v) for v in np.unique(atlas))
    unknown = sorted(present - set(index_to_id) - {0})
    if unknown:
        raise ConvertError("%s holds indices %r that %s does not name" %
                           (atlas_path, unknown[:10], names_path))
    nk, nj, ni = atlas.shape
    # Slice k = NIfTI k (inferior -> superior); image row r = NIfTI j = nj-1-r (anterior at the
    # top); image column c = NIfTI i.
    atlas = atlas[:, ::-1, :].astype(np.int64)
    t1 = t1[:, ::-1, :]
    lut_id = np.zeros(max(index_to_id) + 1, np.uint16)
    for idx, atlas_id in index_to_id.items():
        lut_id[idx] = atlas_id
    ids = lut_id[atlas]  # [z][y][x] original atlas IDs, 0 = background

    colours, min_dist = make_palette(len(entries))
    palette = {"labels": [{"id": 0, "name": "Background", "colour": [0, 0, 0]}]}
    lut_rgb = np.zeros((max(index_to_id) + 1, 3), np.uint8)
    for (idx, name, atlas_id), colour in zip(entries, colours):
        palette["labels"].append({"id": atlas_id, "name": name, "colour": list(colour)})
        lut_rgb[idx] = colour
    seg = lut_rgb[atlas]  # [z][y][x][3]
    log("AAL %dx%dx%d, %d labels (%d regions + background), palette min distance %.1f" %
        (ni, nj, nk, len(palette["labels"]), len(entries), min_dist))

    t1 = np.asarray(t1, np.float64)
    if t1.min() < 0 or t1.max() > 255:
        raise ConvertError("%s: T1 values %g..%g outside 0..255" % (t1_path, t1.min(), t1.max()))
    t1_8 = np.rint(t1).astype(np.uint8)
    for sub in ("seg", "t1", "rgb", "truth"):
        os.makedirs(os.path.join(out_dir, sub))
    for z in range(nk):
        pngio.write_png(os.path.join(out_dir, "seg", "seg_%04d.png" % z), seg[z])
        pngio.write_png(os.path.join(out_dir, "t1", "t1_%04d.png" % z),
                        t1_8[z].astype(np.uint16) * 257)
        pngio.write_png(os.path.join(out_dir, "rgb", "rgb_%04d.png" % z),
                        np.repeat(t1_8[z][:, :, None], 3, axis=2))
    with open(os.path.join(out_dir, "palette.json"), "w") as f:
        json.dump(palette, f, indent=1)
        f.write("\n")
    write_nrrd(os.path.join(out_dir, "truth", "labels.nrrd"), ids, tuple(float(p) for p in pix))
    info = {"source": "mricron-data: aal.nii.gz + aal.nii.txt (AAL atlas), ch2.nii.gz (Colin27 T1)",
            "width": ni, "height": nj, "slices": nk, "spacing_mm": [float(p) for p in pix],
            "labels": len(palette["labels"]), "regions": len(entries),
            "palette_min_distance": round(min_dist, 3),
            "orientation": "column = NIfTI i, row = (height-1) - NIfTI j, slice = NIfTI k",
            "t1": "t1/: 16-bit grey = T1 * 257; rgb/: 8-bit grey RGB = T1"}
    with open(os.path.join(out_dir, "info.json"), "w") as f:
        json.dump(info, f, indent=2)
        f.write("\n")
    log("wrote %d seg, T1 and grey RGB slices, palette.json, truth/labels.nrrd" % nk)


# ------------------------------------------------------------------------------- Visible Woman
# Copies 1..3 of the slice are the original shifted by these whole-pixel amounts (dx, dy), so the
# stack has a known drift: observed_k(p) = original(p - d_k) (docs/ARCHITECTURE.md convention).
VW_SHIFTS = [(0, 0), (2, -1), (3, 1), (1, 2)]


def convert_visible_woman(deb_dir, out_dir):
    src = find_file(deb_dir, "VisibleWomanHeadSlice.png")
    log("reading %s" % os.path.basename(src))
    img = pngio.read_png(src)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ConvertError("%s: expected 8-bit RGB, got %r %s" % (src, img.shape, img.dtype))
    h, w = img.shape[:2]
    os.makedirs(os.path.join(out_dir, "rgb"))
    os.makedirs(os.path.join(out_dir, "truth"))
    shutil.copyfile(src, os.path.join(out_dir, "rgb", "rgb_0000.png"))
    slices = []
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    for k, (dx, dy) in enumerate(VW_SHIFTS):
        if k > 0:
            # observed[y][x] = img[y - dy][x - dx], edges replicated (they are gel).
            ys = np.clip(np.arange(h) - dy, 0, h - 1)
            xs = np.clip(np.arange(w) - dx, 0, w - 1)
            pngio.write_png(os.path.join(out_dir, "rgb", "rgb_%04d.png" % k),
                            img[ys][:, xs])
        slices.append({"index": k, "number": k, "file": "rgb_%04d.png" % k,
                       "dx_px": float(dx), "dy_px": float(dy), "rotation_deg": 0.0,
                       "jump": False, "black": False, "duplicate_of": None})
    transforms = {"width": w, "height": h, "center_px": [cx, cy], "reference_slice": 0,
                  "slices": slices}
    with open(os.path.join(out_dir, "truth", "transforms.json"), "w") as f:
        json.dump(transforms, f, indent=1)
        f.write("\n")
    info = {"source": "insighttoolkit5-examples: VisibleWomanHeadSlice.png", "width": w,
            "height": h, "slices": len(VW_SHIFTS),
            "note": "rgb_0000 is the original file; rgb_0001..3 are shifted copies "
                    "(truth/transforms.json)"}
    with open(os.path.join(out_dir, "info.json"), "w") as f:
        json.dump(info, f, indent=2)
        f.write("\n")
    log("wrote %d RGB slices of %dx%d (1 original + %d shifted copies)" %
        (len(VW_SHIFTS), w, h, len(VW_SHIFTS) - 1))


CONVERTERS = {"head-ct": convert_head_ct, "aal": convert_aal,
              "visible-woman": convert_visible_woman}


def main(argv):
    if len(argv) != 4 or argv[1] not in CONVERTERS:
        print("usage: convert.py {%s} DEB_DIR OUT_DIR" % "|".join(CONVERTERS), file=sys.stderr)
        return 2
    name, deb_dir, out_dir = argv[1:]
    try:
        os.makedirs(out_dir, exist_ok=True)
        if os.listdir(out_dir):
            raise ConvertError("%s: output folder is not empty" % out_dir)
        CONVERTERS[name](deb_dir, out_dir)
    except (ConvertError, OSError, ValueError, tarfile.TarError, plistlib.InvalidFileException) \
            as e:
        print("convert.py: error: %s" % e, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
