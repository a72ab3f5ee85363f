"""The structural PNG check agrees with a full cv2 decode on valid and broken files."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from graspcap.tasks.session.files import ImageKind, image_problems

RNG = np.random.default_rng(7)
IMAGES = {
    "gray16": RNG.integers(0, 65535, (24, 32), dtype=np.uint16),
    "gray8": RNG.integers(0, 255, (24, 32), dtype=np.uint8),
    "bgr8": RNG.integers(0, 255, (24, 32, 3), dtype=np.uint8),
    "bgr16": RNG.integers(0, 65535, (24, 32, 3), dtype=np.uint16),
    "bgra8": RNG.integers(0, 255, (24, 32, 4), dtype=np.uint8),
    "gray16_odd": RNG.integers(0, 65535, (7, 5), dtype=np.uint16),
}


def _rechunk_idat(data: bytes, payload: bytes) -> bytes:
    """Replace the IDAT payload, with a valid CRC (a writer that wrote a broken stream)."""
    pos, out = 8, [data[:8]]
    while pos < len(data):
        length, kind = struct.unpack(">I", data[pos:pos + 4])[0], data[pos + 4:pos + 8]
        chunk = data[pos:pos + 12 + length]
        if kind == b"IDAT":
            chunk = (struct.pack(">I", len(payload)) + kind + payload
                     + struct.pack(">I", zlib.crc32(kind + payload)))
            payload = b""
        out.append(chunk)
        pos += 12 + length
    return b"".join(out)


def _variants(data: bytes) -> dict[str, bytes]:
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x5A
    idat = data.index(b"IDAT") + 4
    stream = zlib.decompress(data[idat:idat + struct.unpack(">I", data[idat - 8:idat - 4])[0]])
    return {
        "valid": data,
        "truncated": data[: len(data) * 2 // 3],
        "no IEND": data[:-12],
        "byte flipped": bytes(flipped),
        "short stream, valid CRC": _rechunk_idat(data, zlib.compress(stream[:-10])),
        "garbage stream, valid CRC": _rechunk_idat(data, b"\x78\x9c" + b"\x00\xff" * 20),
    }


@pytest.mark.parametrize("image_name", sorted(IMAGES))
@pytest.mark.parametrize("kind", list(ImageKind))
def test_fast_png_check_agrees_with_cv2(tmp_path: Path, image_name, kind):
    image = IMAGES[image_name]
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    size = (32, 24)
    for variant, data in _variants(encoded.tobytes()).items():
        path = tmp_path / f"{variant}.png"
        path.write_bytes(data)
        fast = image_problems(path, kind, size)
        full = image_problems(path, kind, size, fast_png=False)
        assert bool(fast) == bool(full), (variant, fast, full)
        if variant == "valid":
            assert fast == full
        else:
            assert fast, variant


def _jpeg_variants(data: bytes) -> dict[str, bytes]:
    sof = max(data.find(b"\xff\xc0"), data.find(b"\xff\xc2"))
    bad_sof = bytearray(data)
    bad_sof[sof + 5 : sof + 9] = b"\x00\x00\x00\x00"  # zero height and width
    return {
        "valid": data,
        "truncated": data[: len(data) * 2 // 3],
        "no SOI": data[2:],
        "zero-size frame header": bytes(bad_sof),
    }


@pytest.mark.parametrize("image_name", ["gray8", "bgr8"])
@pytest.mark.parametrize("kind", [ImageKind.COLOR, ImageKind.DEPTH])
def test_fast_jpeg_check_agrees_with_cv2(tmp_path: Path, image_name, kind):
    """Size and channels from the JPEG frame header, and a 1/8-scale decode, report what a
    full decode reports: the same messages for a valid file, a problem for each broken one."""
    ok, encoded = cv2.imencode(".jpg", IMAGES[image_name])
    assert ok
    for size in [(32, 24), (64, 48)]:
        for variant, data in _jpeg_variants(encoded.tobytes()).items():
            path = tmp_path / f"{variant}.jpg"
            path.write_bytes(data)
            fast = image_problems(path, kind, size)
            full = image_problems(path, kind, size, fast_png=False)
            assert fast == full if variant == "valid" else (fast and full), (variant, fast, full)
