"""Dialects over HTTP (service/dialects.py): a session's channel map and view layer, the service's default
map, and the errors they give."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from service.api.core.config import Settings, SettingsError
from service.cli import main
from service.exr import read_frame
from tests.service.api.conftest import call, exr_post

BLENDER = Path(__file__).resolve().parents[3] / "models" / "data" / "samples" / "blender"
MAP = {"layers": {"color": {"channels": ["beauty.r", "beauty.g", "beauty.b"]},
                  "normal": {"channels": ["n.x", "n.y", "n.z"]}}}


def _exr(channels: dict[str, np.ndarray]) -> bytes:
    sink = io.BytesIO()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                      {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as exr:
        exr.write(sink)
    return sink.getvalue()


def _custom(seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    channels = {f"beauty.{c}": rng.uniform(0.2, 1.0, (16, 24)) for c in "rgb"}
    channels.update({"n.x": np.zeros((16, 24)), "n.y": np.zeros((16, 24)), "n.z": np.ones((16, 24))})
    return _exr(channels)


def _two_view_layers() -> bytes:
    rng = np.random.default_rng(1)
    return _exr({f"{layer}.Combined.{c}": rng.uniform(0.2, 1.0, (16, 24))
                 for layer in ("Front", "Back") for c in "RGBA"})


def _session(url: str, **fields) -> dict:
    answer = call(url, "POST", "/v1/sessions", json.dumps({"pipeline": "flr", "width": 24, "height": 16, **fields}),
                  {"Content-Type": "application/json"})
    return {"status": answer.status, **answer.json()}


def test_a_session_reads_its_frames_with_its_channel_map(make_server):
    url = make_server()
    assert exr_post(url, "/v1/denoise?pipeline=flr", _custom()).status == 422  # no known layer without the map
    info = _session(url, channel_map=MAP)
    assert info["status"] == 201
    for seed in range(2):
        answer = exr_post(url, f"/v1/sessions/{info['id']}/frames", _custom(seed))
        assert answer.status == 200
        assert read_frame(answer.body)["color"].shape == (16, 24, 3)


def test_a_bad_channel_map_is_refused_at_session_creation(make_server):
    url = make_server()
    bad = _session(url, channel_map={"layers": {"colour": {"channels": ["a", "b", "c"]}}})
    assert bad["status"] == 400 and bad["code"] == "invalid_options" and bad["option"] == "channel_map"
    assert "unknown layer 'colour'" in bad["message"]
    info = _session(url, channel_map={"layers": {"color": {"channels": ["x.r", "x.g", "x.b"]}}})
    answer = exr_post(url, f"/v1/sessions/{info['id']}/frames", _custom())
    assert answer.status == 422 and answer.json()["layer"] == "color" and "lacks: x.r" in answer.json()["message"]


def test_view_layers_over_http(make_server):
    url = make_server()
    answer = exr_post(url, "/v1/denoise?pipeline=bilateral", _two_view_layers())
    assert answer.status == 422 and "view layers Back, Front" in answer.json()["message"]
    info = _session(url, pipeline="bilateral", view_layer="Back")
    assert exr_post(url, f"/v1/sessions/{info['id']}/frames", _two_view_layers()).status == 200
    url = make_server(view_layer="Front")
    assert exr_post(url, "/v1/denoise?pipeline=bilateral", _two_view_layers()).status == 200


def test_the_service_default_channel_map(make_server, tmp_path):
    path = tmp_path / "map.json"
    path.write_text(json.dumps(MAP))
    url = make_server(channel_map=str(path))
    assert exr_post(url, "/v1/denoise?pipeline=flr", _custom()).status == 200
    path.write_text("{}")
    with pytest.raises(SettingsError, match="MCDENOISE_CHANNEL_MAP"):
        Settings(channel_map=str(path))


def test_stream_sends_the_channel_map_to_its_session(server, tmp_path, capsys):
    folder = tmp_path / "seq"
    folder.mkdir()
    for t in range(2):
        (folder / f"frame_{t:04d}.exr").write_bytes(_custom(t))
    map_file = tmp_path / "map.json"
    map_file.write_text(json.dumps(MAP))
    args = ["stream", "--pipeline", "flr", "--url", server, "--channel-map", str(map_file), str(folder),
            str(tmp_path / "out")]
    assert main(args) == 0, capsys.readouterr()
    assert len(list((tmp_path / "out").glob("*.exr"))) == 2


def test_a_blender_sequence_streams_as_it_is(server, tmp_path):
    args = ["stream", "--pipeline", "flr", "--url", server, str(BLENDER / "noisy"), str(tmp_path / "out")]
    assert main(args) == 0
    assert len(list((tmp_path / "out").glob("*.exr"))) == 3


def test_two_renders_as_one_two_part_exr_feed_the_split_buffer_pipelines(make_server):
    from service.exr import join_renders

    url = make_server()
    first, second = BLENDER / "noisy" / "frame_0001.exr", BLENDER / "second" / "frame_0001.exr"
    answer = exr_post(url, "/v1/denoise?pipeline=crossregression", first.read_bytes())
    assert answer.status == 422 and answer.json()["layer"] == "colorA"  # one render: no halves
    joined = join_renders(first, second)
    answer = exr_post(url, "/v1/denoise?pipeline=crossregression", joined)
    assert answer.status == 200
    local = read_frame(joined)
    np.testing.assert_allclose(local["color"], 0.5 * (read_frame(first)["color"] + read_frame(second)["color"]))


def test_stream_with_a_second_half_matches_the_cli(server, tmp_path):
    second = ["--second-half", str(BLENDER / "second")]
    cli = ["denoise", "--pipeline", "crossregression", str(BLENDER / "noisy"), str(tmp_path / "cli"), *second]
    assert main(cli) == 0
    streamed = ["stream", "--pipeline", "crossregression", "--url", server, str(BLENDER / "noisy"),
                str(tmp_path / "streamed"), *second]
    assert main(streamed) == 0
    for path in sorted((tmp_path / "cli").glob("*.exr")):  # the server runs 1 numba thread per frame here, the
        # CLI 2: crossregression's rows are split by thread count, so sums differ in float32 rounding only
        np.testing.assert_allclose(read_frame(tmp_path / "streamed" / path.name)["color"],
                                   read_frame(path)["color"], rtol=1e-5, atol=1e-6)


def test_huge_numbers_in_a_session_channel_map_are_a_400(make_server):
    url = make_server()
    spec = {"layers": {"color": {"channels": ["beauty.r", "beauty.g", "beauty.b"], "scale": [1e300, 1, 1]}}}
    bad = _session(url, channel_map=spec)
    assert bad["status"] == 400 and bad["option"] == "channel_map" and "within float32" in bad["message"]


def test_a_two_render_file_counts_both_parts_against_the_memory_budget():
    from service.api import codec
    from service.api.core.errors import ApiError
    from service.exr import join_renders

    size = (512, 512)
    first = {f"color.{c}": np.full(size, 0.5) for c in "RGB"} | {f"junk.{i}": np.zeros(size) for i in range(17)}
    joined = join_renders(_exr(first), _exr({f"color.{c}": np.full(size, 0.5) for c in "RGB"}))
    header = codec.exr_header(joined)
    assert len(header.channels) + len(header.second_channels) == 23
    per_channel = size[0] * size[1] * 4 * codec.MEMORY_FACTOR / 2**20  # MiB
    settings = Settings(max_frame_mb=int(np.ceil(10 * per_channel)))  # a 3-channel read fits, 23 channels do not
    with pytest.raises(ApiError, match="23 channels"):
        codec.decode(joined, settings, ["color"])
    single = _exr(first)
    assert codec.decode(single, settings, ["color"])["color"].shape == (512, 512, 3)
