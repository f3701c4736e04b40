"""An image file's width and height from its header, read before any pixel is decoded.

OpenCV allocates the whole decoded image first and only then finds it too big
for the machine; reading the header lets :func:`~popcode_runtime.geometry.crop.read_image`
refuse a 100-megapixel file in microseconds. PNG, JPEG, BMP and PNM headers are
read here; other formats fall back to OpenCV's own pixel limit.
"""

from __future__ import annotations

import struct
from pathlib import Path

_JPEG_FRAME_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_SIGNATURE_BYTES = 32  # the format's signature, and PNG's and BMP's sizes
_HEADER_BYTES = 1 << 16  # enough for the headers below; JPEG scans further in chunks


def image_size(path: str | Path) -> tuple[int, int] | None:
    """``(width, height)`` from the file's header, or None for formats (or damaged headers) not read here."""
    with open(path, "rb") as handle:
        head = handle.read(_SIGNATURE_BYTES)  # PNG and BMP give their size here; a run checks every image's
        if head.startswith(b"\x89PNG\r\n\x1a\n") and len(head) >= 24:
            return struct.unpack(">II", head[16:24])
        if head.startswith(b"BM") and len(head) >= 26:
            width, height = struct.unpack("<ii", head[18:26])
            return abs(width), abs(height)
        if head[:2] in (b"P1", b"P2", b"P3", b"P4", b"P5", b"P6"):
            return _pnm_size(head + handle.read(_HEADER_BYTES - len(head)))
        if head.startswith(b"\xff\xd8"):
            handle.seek(2)
            return _jpeg_size(handle)
    return None


def _pnm_size(head: bytes) -> tuple[int, int] | None:
    fields: list[int] = []
    for line in head[2:].split(b"\n"):
        for token in line.split(b"#", 1)[0].split():
            if not token.isdigit():
                return None
            fields.append(int(token))
            if len(fields) == 2:
                return fields[0], fields[1]
    return None


def _jpeg_size(handle) -> tuple[int, int] | None:
    """Walk the JPEG segments to the first start-of-frame marker (it holds height, then width)."""
    while True:
        byte = handle.read(1)
        while byte and byte != b"\xff":
            byte = handle.read(1)
        while byte == b"\xff":
            byte = handle.read(1)
        if not byte:
            return None
        marker = byte[0]
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        length_bytes = handle.read(2)
        if len(length_bytes) < 2:
            return None
        length = struct.unpack(">H", length_bytes)[0]
        if marker in _JPEG_FRAME_MARKERS:
            frame = handle.read(5)
            if len(frame) < 5:
                return None
            height, width = struct.unpack(">HH", frame[1:5])
            return width, height
        if length < 2:
            return None
        handle.seek(length - 2, 1)
