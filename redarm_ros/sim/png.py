"""A minimal PNG writer (stdlib zlib + numpy), so snapshots need no imaging library."""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np


def _chunk(kind: bytes, data: bytes) -> bytes:
    return (
        struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    )


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (h, w, 3) RGB or (h, w, 4) RGBA uint8 image (8 bits per channel, no filtering)."""
    img = np.ascontiguousarray(image)
    if (
        img.dtype != np.uint8
        or img.ndim != 3
        or img.shape[2] not in (3, 4)
        or img.shape[0] < 1
        or img.shape[1] < 1
    ):
        raise ValueError(f"expected an (h, w, 3|4) uint8 image, got {img.dtype} {img.shape}")
    h, w, c = img.shape
    color_type = 2 if c == 3 else 6
    raw = np.zeros((h, 1 + w * c), dtype=np.uint8)  # filter byte 0 (None) before every row
    raw[:, 1:] = img.reshape(h, w * c)
    header = struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> str:
    """Write ``image`` (see :func:`encode_png`) to ``path`` atomically (temp file + rename); returns it."""
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as fh:
        fh.write(encode_png(image))
    os.replace(tmp, path)
    return path


def decode_png(data: bytes) -> np.ndarray:
    """Decode what :func:`encode_png` writes (8-bit RGB/RGBA, filter 0 only); for tests and tools."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG")
    pos, idat = 8, b""
    w = h = c = 0
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if zlib.crc32(kind + body) & 0xFFFFFFFF != struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])[0]:
            raise ValueError(f"bad CRC in {kind!r}")
        if kind == b"IHDR":
            w, h, depth, ctype, _, _, _ = struct.unpack(">IIBBBBB", body)
            if depth != 8 or ctype not in (2, 6):
                raise ValueError("only 8-bit RGB/RGBA supported")
            c = 3 if ctype == 2 else 4
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + w * c)
    if np.any(raw[:, 0] != 0):
        raise ValueError("only filter type 0 supported")
    return raw[:, 1:].reshape(h, w, c).copy()
