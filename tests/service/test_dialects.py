"""Renderer dialects (service/dialects.py) on files the renderers wrote themselves: Blender 4.5 Cycles
(models/data/samples/blender, models/data/fixtures/blender_fixture.py) and Mitsuba 3
(models/data/samples/mitsuba, models/data/fixtures/mitsuba_fixture.py), and a user's channel map."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service import pipelines
from service.cli import main
from service.dialects import MISS_DEPTH, ChannelMap, blender, detect
from service.exr import list_sequence, read_channels, read_frame, read_header, write_frame
from service.frame import FrameError, from_two_renders
from service.metrics import rel_l2
from service.stages.reprojection import reproject

SAMPLES = Path(__file__).resolve().parents[2] / "models" / "data" / "samples"
BLENDER = SAMPLES / "blender"


def _frames(folder: Path) -> list:
    return [read_frame(p) for p in list_sequence(folder)]


def _blender_channels(path: Path, name: str) -> np.ndarray:
    channels, _ = read_channels(path)
    return np.stack([channels[f"ViewLayer.{name}.{c}"] for c in "RGB"], axis=-1)


def test_blender_files_are_read_as_blender_with_every_layer():
    header = read_header(BLENDER / "noisy" / "frame_0000.exr")
    assert header.mapping.dialect == "blender"
    assert header.layers == {"color", "albedo", "normal", "depth", "motion", "emission"}
    frame = read_frame(BLENDER / "noisy" / "frame_0000.exr")
    assert frame["albedo"].min() >= 0 and frame["albedo"].max() <= 1  # Cycles adds emission to it
    path = BLENDER / "noisy" / "frame_0001.exr"
    emit, env = _blender_channels(path, "Emit"), _blender_channels(path, "Env")
    np.testing.assert_array_equal(read_frame(path)["emission"], emit + env)


def test_blender_normal_is_world_space_and_misses_are_far():
    frame = read_frame(BLENDER / "reference" / "frame_0001.exr")
    normal, depth = frame["normal"], frame["depth"][..., 0]
    floor = normal[..., 2] > 0.999  # the floor, z up in Blender's world
    assert floor.mean() > 0.3
    np.testing.assert_allclose(normal[floor].mean(axis=0), [0, 0, 1], atol=1e-3)
    sky = _blender_channels(BLENDER / "reference" / "frame_0001.exr", "Env").sum(-1) > 0
    assert np.all(depth[sky & (frame["emission"].sum(-1) == frame["color"].sum(-1))] == np.float32(MISS_DEPTH))


def test_blender_depth_is_the_ray_distance_and_survives_a_skipped_first_sample():
    """Depth.Z is written by sample 0 alone: the halves recipe (sample 0 skipped) leaves it 1e10 everywhere.
    Denoising Depth, which the reader takes, is the distance along the ray: against the planar Depth.Z of
    a full render it grows as 1/cos of the angle off the view axis (50 mm lens: ~1.06 at the frame's side)."""
    channels, _ = read_channels(BLENDER / "noisy" / "frame_0001.exr")
    assert np.all(channels["ViewLayer.Depth.Z"] == np.float32(MISS_DEPTH))
    frame = read_frame(BLENDER / "noisy" / "frame_0001.exr")
    hit = np.abs(frame["normal"]).sum(-1) > 0
    assert hit.mean() > 0.5 and np.median(frame["depth"][hit]) < 100
    reference = read_frame(BLENDER / "reference" / "frame_0001.exr")
    planar = read_channels(BLENDER / "reference" / "frame_0001.exr")[0]["ViewLayer.Depth.Z"]
    both = (planar < 1e9) & (reference["depth"][..., 0] < 1e9)
    ratio = reference["depth"][..., 0] / planar
    height, width = planar.shape
    y, x = np.mgrid[:height, :width]
    radius = np.hypot(x - width / 2 + 0.5, y - height / 2 + 0.5)
    centre, side = np.median(ratio[both & (radius < 8)]), np.median(ratio[both & (radius > 28)])
    assert abs(centre - 1) < 0.02 and 1.03 < side < 1.09


def _warp_error(previous: np.ndarray, current: np.ndarray, motion: np.ndarray, mask: np.ndarray) -> float:
    warped, valid = reproject(previous, motion)
    keep = mask & valid
    return float(np.median((np.abs(warped - current) / (np.abs(current) + 1e-2)).mean(-1)[keep]))


@pytest.mark.parametrize("t", [1, 2])
def test_blender_vector_pass_becomes_backward_motion(t):
    """Warping the previous converged frame by the converted Vector pass lowers the error against the
    current one below zero motion and below every other sign or axis of the pass."""
    frames = _frames(BLENDER / "reference")
    current, previous = frames[t], frames[t - 1]
    mask = (current["depth"][..., 0] < 1e9) & (current["emission"].sum(-1) == 0)  # surfaces, not lights
    motion = current["motion"]
    assert np.abs(motion[mask]).mean() > 1.0  # the camera and the cube move
    ours = _warp_error(previous["color"], current["color"], motion, mask)
    assert ours < 0.9 * _warp_error(previous["color"], current["color"], np.zeros_like(motion), mask)
    for flip in ([-1, 1], [1, -1], [-1, -1]):
        other = motion * np.float32(flip)
        assert ours < 0.8 * _warp_error(previous["color"], current["color"], other, mask), flip


def test_two_blender_renders_with_the_first_sample_skipped_are_independent():
    references = [f["color"] for f in _frames(BLENDER / "reference")]
    first, second = _frames(BLENDER / "noisy"), _frames(BLENDER / "second")
    surface = [(f["emission"].sum(-1) == 0)[..., None] for f in first]
    errors_a, errors_b = (np.concatenate([((f["color"] - r) * s).ravel()
                                          for f, r, s in zip(frames, references, surface, strict=True)])
                          for frames in (first, second))
    assert abs(np.corrcoef(np.clip(errors_a, -1, 1), np.clip(errors_b, -1, 1))[0, 1]) < 0.1
    split = from_two_renders(first[0], second[0])
    np.testing.assert_allclose(split["color"], 0.5 * (first[0]["color"] + second[0]["color"]))


def test_several_view_layers_need_a_name():
    names = [f"{layer}.Combined.{c}" for layer in ("Front", "Back.001") for c in "RGBA"]
    with pytest.raises(FrameError, match="Back.001, Front"):
        blender(names)
    mapping = blender(names, "Back.001")
    assert mapping.layers["color"].channels == ("Back.001.Combined.R", "Back.001.Combined.G", "Back.001.Combined.B")
    with pytest.raises(FrameError, match="no view layer 'Side'"):
        blender(names, "Side")


def test_blender_noisy_image_is_preferred_to_its_denoised_combined():
    names = [f"ViewLayer.{p}.{c}" for p in ("Combined", "Noisy Image") for c in "RGB"]
    assert detect(names).layers["color"].channels[0] == "ViewLayer.Noisy Image.R"


def test_mitsuba_aov_files_are_read_as_mitsuba():
    path = SAMPLES / "mitsuba" / "frame_0000.exr"
    header = read_header(path)
    assert header.mapping.dialect == "mitsuba" and header.layers == {"color", "albedo", "normal", "depth"}
    frame = read_frame(path)
    channels, _ = read_channels(path)
    np.testing.assert_array_equal(frame["color"][..., 0], channels["R"])
    hit = channels["depth.T"] > 0
    assert 0.2 < hit.mean() < 0.9
    assert np.all(frame["depth"][~hit] == np.float32(MISS_DEPTH))
    floor = frame["normal"][..., 1] > 0.999  # the floor, y up in Mitsuba's world (world-space normals)
    assert floor.mean() > 0.1
    np.testing.assert_allclose(frame["normal"][floor].mean(axis=0), [0, 1, 0], atol=1e-3)


def _custom_file(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    channels = {"beauty.r": rng.uniform(0, 1, (4, 6)), "beauty.g": rng.uniform(0, 1, (4, 6)),
                "beauty.b": rng.uniform(0, 1, (4, 6)), "mv.u": np.full((4, 6), 2.0), "mv.v": np.full((4, 6), 3.0)}
    import OpenEXR

    path = tmp_path / "custom.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                      {k: v.astype(np.float32) for k, v in channels.items()}) as exr:
        exr.write(str(path))
    return path


def test_a_channel_map_reads_any_names_with_its_conversions(tmp_path):
    path = _custom_file(tmp_path)
    mapping = ChannelMap.from_json({"layers": {"color": {"channels": ["beauty.r", "beauty.g", "beauty.b"]},
                                               "motion": {"channels": ["mv.u", "mv.v"], "scale": [1, -1]}}})
    frame = read_frame(path, channel_map=mapping)
    assert set(frame.buffers) == {"color", "motion"}
    np.testing.assert_array_equal(frame["motion"][0, 0], [2.0, -3.0])
    assert read_header(path).layers == set()  # without the map: nothing known


@pytest.mark.parametrize(("spec", "message"), [
    ({"layers": {"colour": {"channels": ["a", "b", "c"]}}}, "unknown layer 'colour'"),
    ({"layers": {"color": {"channels": ["a", "b"]}}}, "layer 'color' has 3 channel"),
    ({"layers": {"motion": {"channels": ["a", "b"], "scale": [1]}}}, "layer 'motion' scale"),
    ({"layers": {"depth": {"channels": ["a"], "clip": [2, 1]}}}, "layer 'depth' clip"),
    ({"layers": {"depth": {"channels": ["a"], "gain": 2}}}, "layer 'depth' takes"),
    ({"layer": {}}, "expected an object"),
])
def test_a_bad_channel_map_names_what_is_wrong(spec, message):
    with pytest.raises(ValueError, match=message):
        ChannelMap.from_json(spec)


def test_a_channel_map_naming_absent_channels_is_an_error_naming_the_layer(tmp_path):
    mapping = ChannelMap.from_json({"layers": {"normal": {"channels": ["n.x", "n.y", "n.z"]}}})
    with pytest.raises(FrameError, match="layer 'normal' names channels the file lacks: n.x") as err:
        read_header(_custom_file(tmp_path), mapping)
    assert err.value.layer == "normal"


def test_cli_channel_map_inspect_and_denoise(tmp_path, capsys):
    path = _custom_file(tmp_path)
    folder = tmp_path / "seq"
    folder.mkdir()
    path.rename(folder / "frame_0000.exr")
    map_file = tmp_path / "map.json"
    map_file.write_text(json.dumps({"layers": {"color": {"channels": ["beauty.r", "beauty.g", "beauty.b"]}}}))
    assert main(["inspect", str(folder / "frame_0000.exr"), "--channel-map", str(map_file)]) == 0
    assert "dialect: map" in capsys.readouterr().out
    assert main(["denoise", str(folder), str(tmp_path / "out"), "--channel-map", str(map_file)]) == 0
    assert "pipeline: auto -> bilateral" in capsys.readouterr().out
    map_file.write_text("{")
    assert main(["denoise", str(folder), str(tmp_path / "out"), "--channel-map", str(map_file)]) == 2
    assert "channel map" in capsys.readouterr().err


def _denoised(folder: Path) -> list[np.ndarray]:
    return [read_frame(p)["color"] for p in list_sequence(folder)]


def _mean_error(frames: list[np.ndarray], references: list[np.ndarray]) -> float:
    return float(np.mean([rel_l2(f, r) for f, r in zip(frames, references, strict=True)]))


def test_a_blender_sequence_denoises_through_the_cli(tmp_path, capsys):
    """Every pipeline whose layers one Blender render feeds, below half the noisy relL2."""
    assert main(["denoise", str(BLENDER / "noisy"), str(tmp_path / "auto")]) == 0
    assert "pipeline: auto -> kpn" in capsys.readouterr().out
    references = [f["color"] for f in _frames(BLENDER / "reference")]
    noisy = _frames(BLENDER / "noisy")
    noisy_error = _mean_error([f["color"] for f in noisy], references)
    fed = [n for n in pipelines.names() if not set(pipelines.get(n).requires) - set(noisy[0].buffers)]
    assert {"bilateral", "bmfr", "flr", "rae", "svgf"} <= set(fed)
    for name in fed:
        assert main(["denoise", "--pipeline", name, str(BLENDER / "noisy"), str(tmp_path / name)]) == 0
        error = _mean_error(_denoised(tmp_path / name), references)
        assert error < 0.5 * noisy_error, (name, error, noisy_error)


@pytest.mark.parametrize("name", ["crossregression", "crossreg"])
def test_two_blender_renders_feed_the_split_buffer_pipelines(tmp_path, capsys, name):
    second = ["--second-half", str(BLENDER / "second")]
    if name == "crossregression":
        assert main(["denoise", str(BLENDER / "noisy"), str(tmp_path / "auto"), *second]) == 0
        assert "pipeline: auto (per tile" in capsys.readouterr().out
    assert main(["denoise", "--pipeline", name, str(BLENDER / "noisy"), str(tmp_path / name), *second]) == 0
    references = [f["color"] for f in _frames(BLENDER / "reference")]
    split = [from_two_renders(a, b) for a, b in zip(_frames(BLENDER / "noisy"), _frames(BLENDER / "second"),
                                                    strict=True)]
    noisy_error = _mean_error([f["color"] for f in split], references)
    assert _mean_error(_denoised(tmp_path / name), references) < 0.6 * noisy_error


def test_a_second_render_of_another_length_is_refused(tmp_path, capsys):
    short = tmp_path / "short"
    short.mkdir()
    (short / "frame_0000.exr").write_bytes((BLENDER / "second" / "frame_0000.exr").read_bytes())
    args = ["denoise", "--pipeline", "crossregression", str(BLENDER / "noisy"), str(tmp_path / "o"), "--second-half"]
    assert main([*args, str(short)]) == 2
    assert "has 1 frames" in capsys.readouterr().err


def test_write_frame_round_trips_in_the_frame_format(tmp_path):
    frame = read_frame(BLENDER / "noisy" / "frame_0000.exr")
    write_frame(tmp_path / "f.exr", frame)
    assert read_header(tmp_path / "f.exr").mapping.dialect == "mcdenoise"
    np.testing.assert_array_equal(read_frame(tmp_path / "f.exr")["motion"], frame["motion"])


def test_keep_layers_writes_the_input_with_a_denoised_pass_blender_can_load(tmp_path):
    assert main(["denoise", "--pipeline", "flr", str(BLENDER / "noisy"), str(tmp_path / "plain")]) == 0
    assert main(["denoise", "--pipeline", "flr", "--keep-layers", str(BLENDER / "noisy"), str(tmp_path / "kept")]) == 0
    source = BLENDER / "noisy" / "frame_0001.exr"
    given, given_header = read_channels(source)
    kept, kept_header = read_channels(tmp_path / "kept" / "frame_0001.exr")
    assert set(kept) == set(given) | {"ViewLayer.Denoised.R", "ViewLayer.Denoised.G", "ViewLayer.Denoised.B"}
    for name, pixels in given.items():
        assert kept[name].dtype == pixels.dtype
        np.testing.assert_array_equal(kept[name], pixels)
    assert kept_header["BlenderMultiChannel"] == given_header["BlenderMultiChannel"]
    plain = read_frame(tmp_path / "plain" / "frame_0001.exr")["color"]
    np.testing.assert_array_equal(np.stack([kept[f"ViewLayer.Denoised.{c}"] for c in "RGB"], -1), plain)
    assert read_header(tmp_path / "kept" / "frame_0001.exr").mapping.dialect == "blender"


# ------------------------------------------------------------------------------- edge cases (review)


def _write_exr(path: Path, channels: dict[str, np.ndarray], **header) -> Path:
    import OpenEXR

    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, **header},
                      {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as exr:
        exr.write(str(path))
    return path


def _plane(value: float = 0.5, shape: tuple[int, int] = (4, 6)) -> np.ndarray:
    return np.full(shape, value, np.float32)


def test_frame_format_channels_in_a_blender_file_are_read_beside_its_passes(tmp_path):
    channels = {f"ViewLayer.Combined.{c}": _plane() for c in "RGBA"}
    channels.update({f"ViewLayer.Denoising Albedo.{c}": _plane(0.3) for c in "RGB"})
    channels.update({f"reference.{c}": _plane(0.4) for c in "RGB"})
    frame = read_frame(_write_exr(tmp_path / "f.exr", channels))
    assert set(frame.buffers) == {"color", "albedo", "reference"}
    np.testing.assert_array_equal(frame["reference"], np.float32(0.4))


def test_mitsuba_keeps_aovs_named_after_our_layers(tmp_path):
    channels = {c: _plane() for c in "RGB"} | {"depth.T": _plane(2.0)}
    channels.update({f"normal.{c}": _plane(v) for c, v in zip("XYZ", (0.0, 1.0, 0.0), strict=True)})
    channels.update({f"reference.{c}": _plane(0.4) for c in "RGB"})
    header = read_header(_write_exr(tmp_path / "m.exr", channels))
    assert header.mapping.dialect == "mitsuba" and header.layers == {"color", "normal", "depth", "reference"}


def test_not_view_layers_are_not_blender(tmp_path):
    # a multilayer file without view-layer passes (a compositor output), and an AOV whose name holds a dot
    plain = read_header(_write_exr(tmp_path / "p.exr", {f"Image.{c}": _plane() for c in "RGB"},
                                   BlenderMultiChannel="Blender V2.55.1 and newer"))
    assert plain.mapping.dialect == "mcdenoise"
    names = [f"ViewLayer.Combined.{c}" for c in "RGBA"] + ["ViewLayer.my.Depth.Z"]
    assert detect(names).dialect == "blender"  # one view layer, no phantom "ViewLayer.my"


def test_numbers_of_a_channel_map_must_be_finite_float32():
    for spec in ({"scale": [10**400, 1, 1]}, {"clip": [0, 10**400]}, {"scale": [True, 1, 1]},
                 {"replace_zero": "1"}, {"clip": [0, 1e39]}):
        with pytest.raises(ValueError, match="finite numbers within float32"):
            ChannelMap.from_json({"layers": {"color": {"channels": ["a", "b", "c"], **spec}}})


def test_clipping_leaves_nan_and_inf_for_the_frame_to_repair_and_count(tmp_path):
    albedo = _plane(0.5)
    albedo[0, 0] = np.inf
    channels = {f"ViewLayer.Combined.{c}": _plane() for c in "RGB"}
    channels.update({f"ViewLayer.Denoising Albedo.{c}": albedo for c in "RGB"})
    frame = read_frame(_write_exr(tmp_path / "f.exr", channels))
    assert frame.nonfinite["albedo"] == 3 and frame["albedo"].max() <= 1


def test_two_renders_in_one_file(tmp_path):
    from service.exr import join_renders, read_layers

    first = _write_exr(tmp_path / "a.exr", {f"color.{c}": _plane(0.2) for c in "RGB"} | {"albedo.R": _plane(),
                       "albedo.G": _plane(), "albedo.B": _plane()})
    second = _write_exr(tmp_path / "b.exr", {f"color.{c}": _plane(0.6) for c in "RGB"} | {"depth.Z": _plane()})
    joined = join_renders(first, second)
    header = read_header(joined)
    assert header.second_channels == ("color.B", "color.G", "color.R")  # only the second render's colour
    for layers in (("color", "albedo"), ("colorA", "colorB", "albedo"), ("colorB",)):
        out = read_layers(joined, header, layers)
        np.testing.assert_array_equal(out["colorB"], np.float32(0.6))
    frame = read_frame(joined)
    np.testing.assert_allclose(frame["color"], 0.4)
    small = _write_exr(tmp_path / "s.exr", {f"color.{c}": _plane(0.6, (2, 6)) for c in "RGB"})
    with pytest.raises(FrameError, match="the second render is 6x2 but the first is 6x4") as err:
        join_renders(first, small)
    assert err.value.layer == "colorB"


def test_only_two_parts_named_by_join_renders_are_two_renders(tmp_path):
    import io

    import OpenEXR

    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION}, {f"{c}": _plane(v) for c in "RGB"}, name=name)
             for name, v in (("rgba", 0.2), ("diffuse", 0.6), ("albedo", 0.5))]
    sink = io.BytesIO()
    with OpenEXR.File(parts) as exr:
        exr.write(sink)
    header = read_header(sink.getvalue())
    assert header.second is None and header.layers == {"color"}
    np.testing.assert_array_equal(read_frame(sink.getvalue())["color"], np.float32(0.2))


def test_a_second_render_of_another_size_is_refused_from_the_header(tmp_path):
    import io

    import OpenEXR

    def window(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        return np.array([0, 0], np.int32), np.array([width - 1, height - 1], np.int32)

    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "displayWindow": window(60, 40),
                           "dataWindow": window(shape[1], shape[0])},
                          {f"color.{c}": _plane(0.2, shape) for c in "RGB"}, name=name)
             for name, shape in (("first", (4, 6)), ("second", (40, 60)))]
    sink = io.BytesIO()
    with OpenEXR.File(parts) as exr:
        exr.write(sink)
    with pytest.raises(FrameError, match="second render is 60x40 but the first is 6x4"):
        read_header(sink.getvalue())


def test_two_renders_count_repaired_values_once():
    from service.frame import Frame

    color = np.full((2, 2, 3), 0.5, np.float32)
    color[0, 0, 0] = np.nan
    first = Frame.from_buffers({"color": color})
    split = from_two_renders(first, Frame.from_buffers({"color": np.full((2, 2, 3), 0.5, np.float32)}))
    assert split.nonfinite == {"colorA": 1} and split.nonfinite_total == 1


def test_keep_layers_keeps_the_data_window(tmp_path):
    from service.dialects import native
    from service.exr import write_with_input

    window = (np.array([8, 4], np.int32), np.array([13, 7], np.int32))
    source = _write_exr(tmp_path / "w.exr", {f"color.{c}": _plane() for c in "RGB"}, dataWindow=window,
                        displayWindow=(np.array([0, 0], np.int32), np.array([63, 63], np.int32)))
    write_with_input(tmp_path / "out.exr", source, np.zeros((4, 6, 3), np.float32), native(["color.R"]))
    _, header = read_channels(tmp_path / "out.exr")
    np.testing.assert_array_equal(header["dataWindow"][0], [8, 4])
    np.testing.assert_array_equal(header["displayWindow"][1], [63, 63])
