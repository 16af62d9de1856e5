"""Minimal PNG writer/reader with zlib + struct (no PIL): 8/16-bit grey and RGB, no interlace.

Used by fetch-sample-data.sh to turn the Debian sample data into slice folders. Files are written
deterministically (fixed compression level, no timestamps) and atomically (temp file + rename).
"""
import os
import struct
import zlib

import numpy as np

_SIG = b"\x89PNG\r\n\x1a\n"


def _chunk(kind, data):
    return (struct.pack(">I", len(data)) + kind + data +
            struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def encode_png(image):
    """PNG bytes of a (H, W) or (H, W, 3) uint8/uint16 array (16-bit stored big-endian)."""
    a = np.asarray(image)
    if a.dtype not in (np.uint8, np.uint16):
        raise ValueError("encode_png: dtype %s not uint8/uint16" % a.dtype)
    if a.ndim == 2:
        colour_type, channels = 0, 1
    elif a.ndim == 3 and a.shape[2] == 3:
        colour_type, channels = 2, 3
    else:
        raise ValueError("encode_png: shape %s is not (H,W) or (H,W,3)" % (a.shape,))
    h, w = a.shape[:2]
    bits = 8 if a.dtype == np.uint8 else 16
    rows = np.ascontiguousarray(a.astype(">u2") if bits == 16 else a).view(np.uint8)
    rows = rows.reshape(h, w * channels * bits // 8)
    raw = np.zeros((h, rows.shape[1] + 1), np.uint8)  # filter byte 0 (None) per row
    raw[:, 1:] = rows
    ihdr = struct.pack(">IIBBBBB", w, h, bits, colour_type, 0, 0, 0)
    return (_SIG + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) +
            _chunk(b"IEND", b""))


def write_png(path, image):
    """Writes `image` as PNG at `path` atomically."""
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(encode_png(image))
    os.replace(tmp, path)


def _unfilter(data, h, stride, bpp):
    out = np.zeros((h, stride), np.int32)
    pos = 0
    prev = np.zeros(stride, np.int32)
    for y in range(h):
        ftype = data[pos]
        line = np.frombuffer(data, np.uint8, stride, pos + 1).astype(np.int32)
        pos += stride + 1
        if ftype == 0:
            cur = line
        elif ftype == 1:
            cur = line.copy()
            for x in range(bpp, stride):
                cur[x] = (cur[x] + cur[x - bpp]) & 0xFF
        elif ftype == 2:
            cur = (line + prev) & 0xFF
        elif ftype == 3:
            cur = line.copy()
            for x in range(stride):
                left = cur[x - bpp] if x >= bpp else 0
                cur[x] = (cur[x] + ((left + prev[x]) >> 1)) & 0xFF
        elif ftype == 4:
            cur = line.copy()
            for x in range(stride):
                a = cur[x - bpp] if x >= bpp else 0
                b = prev[x]
                c = prev[x - bpp] if x >= bpp else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                cur[x] = (cur[x] + pred) & 0xFF
        else:
            raise ValueError("PNG: bad filter type %d in row %d" % (ftype, y))
        out[y] = cur
        prev = cur
    return out.astype(np.uint8)


def read_png(path):
    """Reads an 8/16-bit grey, grey+alpha, RGB or RGBA non-interlaced PNG into a numpy array
    ((H, W) or (H, W, C)); 16-bit comes back as uint16. Slow (pure Python filters) but only used
    for a single small sample image."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:8] != _SIG:
        raise ValueError("%s: not a PNG file" % path)
    pos, idat, hdr = 8, [], None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if hdr is None:
        raise ValueError("%s: PNG has no IHDR" % path)
    w, h, bits, colour_type, _, _, interlace = hdr
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(colour_type)
    if channels is None or bits not in (8, 16) or interlace:
        raise ValueError("%s: unsupported PNG (colour type %d, %d bit, interlace %d)" %
                         (path, colour_type, bits, interlace))
    bpp = channels * bits // 8
    raw = zlib.decompress(b"".join(idat))
    px = _unfilter(raw, h, w * bpp, bpp)
    if bits == 16:
        px = px.reshape(h, -1).view(">u2").astype(np.uint16)
    a = px.reshape(h, w, channels)
    return a[:, :, 0] if channels == 1 else a
