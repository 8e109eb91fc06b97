import subprocess
import sys

import numpy as np
import OpenEXR

from service.cli import main
from service.exr import read_frame, write_frame


def test_denoise_end_to_end_in_a_subprocess(tiny_sequence_dir, tmp_path):
    out = tmp_path / "out"
    run = subprocess.run(
        [sys.executable, "-m", "service", "denoise", str(tiny_sequence_dir), str(out), "--png",
         "--pipeline", "bilateral", "-o", "radius=3"],
        capture_output=True, text=True, check=False,
    )
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[1].startswith("frame_0000.exr") and "bilateral: 3 frames" in run.stdout
    for t in range(3):
        frame = read_frame(out / f"frame_{t:04d}.exr")
        assert set(frame.buffers) == {"color"} and frame["color"].shape == (24, 40, 3)
        assert (out / f"frame_{t:04d}.png").read_bytes().startswith(b"\x89PNG")


def test_bad_frame_exits_nonzero_with_one_line_reason(tiny_sequence_dir, tmp_path, capsys):
    write_frame(tiny_sequence_dir / "frame_0001.exr", {"albedo": np.ones((24, 40, 3), np.float32)})
    code = main(["denoise", "--pipeline", "bilateral", str(tiny_sequence_dir), str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == ("error: frame_0001.exr: missing layer 'color' required by pipeline 'bilateral' "
                   "(frame has: albedo)")


def test_missing_folder_and_unknown_pipeline_and_bad_option(tmp_path, tiny_sequence_dir, capsys):
    assert main(["denoise", str(tmp_path / "none"), str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["denoise", "--pipeline", "nope", str(tiny_sequence_dir), str(tmp_path / "o")]) == 2
    assert "unknown pipeline 'nope'" in capsys.readouterr().err
    assert main(["denoise", "-o", "radius", str(tiny_sequence_dir), str(tmp_path / "o")]) == 2
    assert "is not KEY=VALUE" in capsys.readouterr().err


def test_pipelines_lists_layers(capsys):
    assert main(["pipelines"]) == 0
    out = capsys.readouterr().out
    assert "crossregression [default]" in out and "requires: color" in out


def test_inspect_reports_types_stats_and_nans(tmp_path, capsys):
    color = np.ones((3, 4, 3), np.float32)
    color[0, 0, 0] = np.nan
    write_frame(tmp_path / "f.exr", {"color": color, "depth": np.full((3, 4, 1), 2.0)}, half=True)
    assert main(["inspect", str(tmp_path / "f.exr")]) == 0
    out = capsys.readouterr().out
    assert "4x3, 4 channels" in out
    row = next(line for line in out.splitlines() if line.startswith("color.R"))
    assert row.split()[1:] == ["half", "1", "1", "1", "1", "0"]
    assert next(line for line in out.splitlines() if line.startswith("depth.Z")).split()[2] == "2"


def test_auto_picks_the_preferred_pipeline_the_frames_can_feed(tiny_sequence_dir, tmp_path, capsys):
    assert main(["denoise", str(tiny_sequence_dir), str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("pipeline: auto (per tile") and "auto: 3 frames" in out
    with OpenEXR.File(str(tmp_path / "o" / "frame_0000.exr")) as written:  # `error` is output-only: readers skip it
        assert set(written.channels()) == {"color", "error.Y"}
        error = written.channels()["error.Y"].pixels
        assert error.shape == (24, 40) and np.isfinite(error).all()
    only_color = tmp_path / "c"
    write_frame(only_color / "frame_0000.exr", {"color": np.ones((4, 4, 3), np.float32)})
    assert main(["denoise", str(only_color), str(tmp_path / "o2")]) == 0
    assert capsys.readouterr().out.startswith("pipeline: auto -> bilateral (")


def test_the_parser_knows_auto_without_importing_the_pipelines():
    from service import pipelines
    from service.cli.sequence_args import AUTO

    assert AUTO == pipelines.AUTO
