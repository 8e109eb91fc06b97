"""PNG previews of HDR radiance: exposure, Reinhard-style tone map, sRGB transfer, 8-bit PNG.

No imaging library: the PNG encoder is the few lines the format needs (zlib-compressed RGB rows)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np


def tonemap(color: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """color: (H, W, 3) float32 linear HDR radiance. Returns (H, W, 3) uint8 sRGB for display.

    Per-channel x / (1 + x) after exposure, then the sRGB transfer curve; negative values show black.
    """
    x = np.maximum(np.nan_to_num(color.astype(np.float32) * exposure, nan=0.0, posinf=1e30), 0.0)
    x = x / (1.0 + x)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.rint(srgb * 255.0), 0, 255).astype(np.uint8)


def encode_png(rgb: np.ndarray) -> bytes:
    """rgb: (H, W, 3) uint8. Returns PNG file bytes (8-bit truecolour, no interlace)."""
    height, width = rgb.shape[:2]
    rows = np.concatenate([np.zeros((height, 1), np.uint8), rgb.reshape(height, width * 3)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def write_preview(path: str | Path, color: np.ndarray, exposure: float = 1.0) -> None:
    """Write a tone-mapped PNG of `color` ((H, W, 3) float32 linear radiance) to `path`."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(encode_png(tonemap(color, exposure)))
