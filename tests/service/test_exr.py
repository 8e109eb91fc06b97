import numpy as np
import OpenEXR
import pytest

from service.exr import (
    encode_frame,
    list_sequence,
    read_channels,
    read_frame,
    read_header,
    read_metadata,
    write_frame,
)
from service.frame import Frame, FrameError
from tests.tolerances import HALF_RTOL


def _layers(rng, h=7, w=13):
    return {
        "color": rng.normal(size=(h, w, 3)).astype(np.float32) * 10,
        "albedo": rng.random((h, w, 3), dtype=np.float32),
        "normal": rng.normal(size=(h, w, 3)).astype(np.float32),
        "depth": rng.random((h, w, 1), dtype=np.float32) * 100,
        "motion": rng.normal(size=(h, w, 2)).astype(np.float32),
        "sampleCount": np.full((h, w, 1), 16, np.float32),
    }


def _write_raw(path, channels):
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def test_float_round_trip_is_exact(tmp_path):
    layers = _layers(np.random.default_rng(0))
    write_frame(tmp_path / "f.exr", layers)
    frame = read_frame(tmp_path / "f.exr")
    assert set(frame.buffers) == set(layers)
    for name, value in layers.items():
        np.testing.assert_array_equal(frame[name], value)


def test_half_round_trip_within_half_precision(tmp_path):
    layers = _layers(np.random.default_rng(1))
    write_frame(tmp_path / "h.exr", layers, half=True)
    channels, _ = read_channels(tmp_path / "h.exr")
    assert all(c.dtype == np.float16 for c in channels.values())
    frame = read_frame(tmp_path / "h.exr")
    for name, value in layers.items():
        assert frame[name].dtype == np.float32
        np.testing.assert_allclose(frame[name], value, rtol=HALF_RTOL, atol=1e-4)


def test_bytes_round_trip_equals_file_round_trip(tmp_path):
    layers = _layers(np.random.default_rng(2))
    frame = read_frame(encode_frame(layers))
    for name, value in layers.items():
        np.testing.assert_array_equal(frame[name], value)


def test_channels_in_any_order_and_mixed_types(tmp_path):
    h, w = 3, 4
    r, g, b = (np.full((h, w), v, np.float32) for v in (1.0, 2.0, 3.0))
    _write_raw(tmp_path / "m.exr", {"color.B": b.astype(np.float16), "color.R": r, "color.G": g,
                                    "normal.Z": b, "normal.X": r, "normal.Y": g})
    frame = read_frame(tmp_path / "m.exr")
    np.testing.assert_array_equal(frame["color"][0, 0], [1, 2, 3])
    np.testing.assert_array_equal(frame["normal"][0, 0], [1, 2, 3])


def test_bare_rgb_is_color_and_rgb_names_serve_xyz_layers(tmp_path):
    one = np.ones((2, 2), np.float32)
    _write_raw(tmp_path / "b.exr", {"R": one, "G": 2 * one, "B": 3 * one, "A": one,
                                    "normal.R": one, "normal.G": 0 * one, "normal.B": 0 * one, "depth.V": 5 * one})
    frame = read_frame(tmp_path / "b.exr")
    np.testing.assert_array_equal(frame["color"][1, 1], [1, 2, 3])
    np.testing.assert_array_equal(frame["normal"][1, 1], [1, 0, 0])
    assert frame["depth"][0, 0, 0] == 5


def test_unknown_layers_are_ignored(tmp_path):
    one = np.ones((2, 2), np.float32)
    _write_raw(tmp_path / "u.exr", {"color.R": one, "color.G": one, "color.B": one, "cryptomatte.R": one})
    assert set(read_frame(tmp_path / "u.exr").buffers) == {"color"}


def test_missing_channel_names_the_layer(tmp_path):
    one = np.ones((2, 2), np.float32)
    _write_raw(tmp_path / "c.exr", {"color.R": one, "color.G": one, "color.B": one,
                                    "motion.X": one})
    with pytest.raises(FrameError, match=r"layer 'motion' has 1 channel\(s\) \(X\); expected 2 \(X Y\)") as err:
        read_frame(tmp_path / "c.exr")
    assert err.value.layer == "motion"


def test_extra_channel_is_a_wrong_channel_count(tmp_path):
    one = np.ones((2, 2), np.float32)
    _write_raw(tmp_path / "e.exr", {"color.R": one, "color.G": one, "color.B": one,
                                    "depth.Z": one, "depth.W": one})
    with pytest.raises(FrameError, match="layer 'depth' has 2 channel"):
        read_frame(tmp_path / "e.exr")


def test_nan_in_file_is_repaired_and_counted(tmp_path):
    color = np.ones((3, 3, 3), np.float32)
    color[1, 1, 1] = np.nan
    write_frame(tmp_path / "n.exr", {"color": color})
    frame = read_frame(tmp_path / "n.exr")
    assert frame.nonfinite == {"color": 1} and frame["color"][1, 1, 1] == 0


@pytest.mark.parametrize("data", [b"", b"not an exr at all", None])
def test_garbage_and_truncated_bytes_are_a_clear_error(data):
    if data is None:  # a real EXR cut in half
        data = encode_frame({"color": np.ones((16, 16, 3), np.float32)})[:200]
    with pytest.raises(FrameError, match="not a readable OpenEXR image"):
        read_frame(data)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(FrameError, match="not a readable OpenEXR image"):
        read_frame(tmp_path / "absent.exr")


def test_sequence_listing_sorts_and_reads_metadata(tmp_path):
    for name in ("frame_0002.exr", "frame_0000.exr", "frame_0001.exr", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sequence.json").write_text('{"spp": 4}')
    assert [p.name for p in list_sequence(tmp_path)] == ["frame_0000.exr", "frame_0001.exr", "frame_0002.exr"]
    assert read_metadata(tmp_path) == {"spp": 4}


def test_empty_or_absent_sequence_folder_is_an_error(tmp_path):
    with pytest.raises(FrameError, match="holds no .exr"):
        list_sequence(tmp_path)
    with pytest.raises(FrameError, match="does not exist"):
        list_sequence(tmp_path / "nope")


def test_writing_an_unknown_layer_is_refused(tmp_path):
    with pytest.raises(FrameError, match="unknown layer 'beauty'"):
        write_frame(tmp_path / "x.exr", {"beauty": np.zeros((2, 2, 3))})


def test_frame_object_can_be_written(tmp_path, tiny_frame: Frame):
    write_frame(tmp_path / "t.exr", tiny_frame)
    again = read_frame(tmp_path / "t.exr")
    np.testing.assert_array_equal(again["bcM3"], tiny_frame["bcM3"])


def test_header_gives_size_and_layers_of_the_decoded_frame(tmp_path):
    one = np.ones((2, 2), np.float32)
    channels = {"R": one, "G": one, "B": one, "colorA.R": one, "colorA.G": one, "colorA.B": one,
                "colorB.R": one, "colorB.G": one, "colorB.B": one, "depth.Z": one, "cryptomatte.R": one}
    _write_raw(tmp_path / "l.exr", channels)
    header = read_header(tmp_path / "l.exr")
    assert header.layers == set(read_frame(tmp_path / "l.exr").buffers) == {"color", "colorA", "colorB", "depth"}
    assert (header.width, header.height) == (2, 2)
    data = encode_frame({"colorA": np.ones((3, 5, 3)), "colorB": np.ones((3, 5, 3))})
    assert read_header(data) == read_header(data) and read_header(data).layers == {"color", "colorA", "colorB"}
    assert (read_header(data).width, read_header(data).height) == (5, 3)
    with pytest.raises(FrameError, match="not a readable OpenEXR image"):
        read_header(tmp_path / "absent.exr")
    with pytest.raises(FrameError, match="not a readable OpenEXR image"):
        read_header(data[:20])
