import struct
import zlib

import numpy as np

from service.preview import encode_png, tonemap


def test_tonemap_range_and_monotonic():
    x = np.array([[[-1.0, 0.0, 1.0], [1e30, np.nan, 0.5]]], np.float32)
    y = tonemap(x)
    assert y.dtype == np.uint8 and y[0, 0, 0] == 0 and y[0, 0, 1] == 0 and y[0, 1, 0] == 255
    assert y[0, 0, 2] > y[0, 1, 2] > 0


def test_png_decodes_back_to_pixels():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    png = encode_png(rgb)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (3, 2)
    idat_len = struct.unpack(">I", png[33:37])[0]
    raw = zlib.decompress(png[41:41 + idat_len])
    rows = np.frombuffer(raw, np.uint8).reshape(2, 1 + 9)
    assert np.all(rows[:, 0] == 0)
    np.testing.assert_array_equal(rows[:, 1:].reshape(2, 3, 3), rgb)
