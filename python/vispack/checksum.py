"""xxHash64 with seed 0, as format/SPEC.md ("Checksums") uses it.

Uses Debian's python3-xxhash (C speed) when it is installed, else a pure-Python implementation
written from the public algorithm description (correct, but about 1000x slower: fine for tests and
small files, slow for whole-file verification of big volumes).
"""
import struct

import numpy as np

try:  # optional: python3-xxhash
    import xxhash as _xxhash
except ImportError:  # pragma: no cover - depends on the machine
    _xxhash = None

_P1, _P2, _P3, _P4, _P5 = (0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9,
                           0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5)
_M = (1 << 64) - 1


def have_fast_xxh64():
    """True when the C implementation (python3-xxhash) is available."""
    return _xxhash is not None


def xxh64(data, seed=0):
    """xxHash64 of a bytes-like object (bytes, memoryview, mmap slice) as an int in [0, 2^64)."""
    if _xxhash is not None:
        return _xxhash.xxh64_intdigest(data, seed)
    return xxh64_pure(data, seed)


def _rotl(x, r):
    return ((x << r) | (x >> (64 - r))) & _M


def _round(acc, lane):
    return (_rotl((acc + lane * _P2) & _M, 31) * _P1) & _M


def _merge(acc, v):
    return ((acc ^ _round(0, v)) * _P1 + _P4) & _M


def _avalanche(h):
    h ^= h >> 33
    h = (h * _P2) & _M
    h ^= h >> 29
    h = (h * _P3) & _M
    h ^= h >> 32
    return h


def _stripes(data, n, seed):
    """The 32-byte stripe loop over data[0 : n - n % 32]; returns the folded accumulator."""
    v1, v2, v3, v4 = (seed + _P1 + _P2) & _M, (seed + _P2) & _M, seed, (seed - _P1) & _M
    lanes = np.frombuffer(data[: n - n % 32], dtype="<u8").tolist()
    for j in range(0, len(lanes), 4):
        v1 = _round(v1, lanes[j])
        v2 = _round(v2, lanes[j + 1])
        v3 = _round(v3, lanes[j + 2])
        v4 = _round(v4, lanes[j + 3])
    h = (_rotl(v1, 1) + _rotl(v2, 7) + _rotl(v3, 12) + _rotl(v4, 18)) & _M
    for v in (v1, v2, v3, v4):
        h = _merge(h, v)
    return h


def xxh64_pure(data, seed=0):
    """Pure-Python xxHash64 (the reference the fast path is tested against)."""
    data = memoryview(data).cast("B")
    n = len(data)
    h = _stripes(data, n, seed) if n >= 32 else (seed + _P5) & _M
    i = n - n % 32
    h = (h + n) & _M
    while i + 8 <= n:
        k = struct.unpack_from("<Q", data, i)[0]
        h = ((_rotl(h ^ _round(0, k), 27) * _P1) + _P4) & _M
        i += 8
    if i + 4 <= n:
        k = struct.unpack_from("<I", data, i)[0]
        h = ((_rotl(h ^ ((k * _P1) & _M), 23) * _P2) + _P3) & _M
        i += 4
    while i < n:
        h = (_rotl(h ^ ((data[i] * _P5) & _M), 11) * _P1) & _M
        i += 1
    return _avalanche(h)
