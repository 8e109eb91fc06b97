import numpy as np
import pytest

from service.frame import LAYERS, Frame, FrameError


def _rgb(h=4, w=5, value=1.0):
    return np.full((h, w, 3), value, np.float32)


def test_buffers_become_float32_hwc_and_single_channel_gets_an_axis():
    frame = Frame.from_buffers({"color": _rgb().astype(np.float64), "depth": np.ones((4, 5))})
    assert frame["color"].dtype == np.float32 and frame["color"].flags.c_contiguous
    assert frame["depth"].shape == (4, 5, 1)
    assert (frame.height, frame.width) == (4, 5)


def test_color_is_mean_of_half_buffers_when_absent():
    frame = Frame.from_buffers({"colorA": _rgb(value=1.0), "colorB": _rgb(value=3.0)})
    np.testing.assert_array_equal(frame["color"], 2.0)


def test_unknown_layers_are_ignored():
    frame = Frame.from_buffers({"color": _rgb(), "myLayer": np.zeros((9, 9, 7))})
    assert "myLayer" not in frame


def test_no_known_layer_is_an_error():
    with pytest.raises(FrameError, match="no known layer"):
        Frame.from_buffers({"beauty": _rgb()})


def test_wrong_channel_count_names_the_layer():
    with pytest.raises(FrameError, match=r"layer 'normal' has shape \(4, 5, 2\); expected \(H, W, 3\)") as err:
        Frame.from_buffers({"color": _rgb(), "normal": np.zeros((4, 5, 2))})
    assert err.value.layer == "normal"


def test_size_mismatch_names_both_layers():
    with pytest.raises(FrameError, match="layer 'albedo' is 6x4 but layer 'color' is 5x4") as err:
        Frame.from_buffers({"color": _rgb(), "albedo": _rgb(4, 6)})
    assert err.value.layer == "albedo"


def test_empty_frame_is_an_error():
    with pytest.raises(FrameError, match="empty"):
        Frame.from_buffers({"color": np.zeros((0, 5, 3))})


def test_non_numeric_dtype_is_an_error():
    with pytest.raises(FrameError, match="dtype"):
        Frame.from_buffers({"color": np.full((2, 2, 3), "x")})


def test_nan_and_inf_are_repaired_and_counted_per_layer():
    color = _rgb()
    color[0, 0, 0] = np.nan
    color[1, 1, :] = np.inf
    normal = np.zeros((4, 5, 3), np.float32)
    normal[2, 2, 1] = -np.inf
    depth = np.full((4, 5, 1), 3.0, np.float32)
    depth[0, 0] = 7.0
    depth[3, 3] = np.nan
    frame = Frame.from_buffers({"color": color, "normal": normal, "depth": depth})
    assert frame.nonfinite == {"color": 4, "normal": 1, "depth": 1}
    assert frame.nonfinite_total == 6
    assert frame["color"][0, 0, 0] == 0 and np.all(frame["color"][1, 1] == 0)
    assert frame["normal"][2, 2, 1] == 0
    assert frame["depth"][3, 3, 0] == 7.0  # the largest finite depth stands for 'nothing hit'


def test_float64_overflow_is_repaired_not_propagated():
    color = np.full((2, 2, 3), 1e300)
    frame = Frame.from_buffers({"color": color})
    assert np.isfinite(frame["color"]).all() and frame.nonfinite["color"] == 12


def test_require_names_missing_layer():
    frame = Frame.from_buffers({"color": _rgb()})
    with pytest.raises(FrameError, match="missing layer 'albedo' required by pipeline 'x'") as err:
        frame.require(["color", "albedo"], who="pipeline 'x'")
    assert err.value.layer == "albedo"


def test_every_layer_has_channels_and_meaning():
    assert {"color", "colorA", "colorB", "albedo", "normal", "depth", "motion", "motionDual", "roughness",
            "ao", "sampleCount", "bcMean", "bcM2", "bcM3", "emission", "error", "reference"} == set(LAYERS)
    assert all(spec.channels and spec.meaning for spec in LAYERS.values())
