import io
import time

import numba
import numpy as np
import pytest

from service import pipelines
from service.cli import main
from service.frame import LAYERS
from service.warmup import WARMUP_SIZE, CompileNotice, warm_up, warmup_frame


def test_warmup_frame_has_every_layer_valid():
    frame = warmup_frame(*WARMUP_SIZE)
    assert [name for name in LAYERS if name not in frame] == ["reference"]
    np.testing.assert_allclose(np.linalg.norm(frame["normal"], axis=-1), 1.0, rtol=1e-5)
    assert (frame["sampleCount"] > 0).all() and not frame["emission"].any()


@pytest.mark.parametrize("name", pipelines.names())
def test_every_pipeline_warms_up_on_the_generated_frames(name):
    warm_up(pipelines.get(name))  # raises what the pipeline raises


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _fresh_kernel():
    """A numba function that no cache holds (a new closure object each call), compiled at its first call."""

    @numba.njit
    def kernel(x):
        return x * 2.0 + 1.0

    return kernel


def test_compile_notice_draws_a_progress_line_while_kernels_compile_and_a_final_one():
    stream = _Terminal()
    with CompileNotice("demo", stream=stream, interval=0.01) as notice:
        kernel = _fresh_kernel()
        assert kernel(1.0) == 3.0
        time.sleep(0.05)  # the drawing thread's turn
    text = stream.getvalue()
    assert "\rcompiling kernels for demo (first run, cached after)..." in text
    final = text.rsplit("\r\033[K", 1)[1]  # the progress line is cleared for the final one
    assert final.startswith("compiled kernels for demo in ") and final.endswith("\n") and final.count("\n") == 1
    assert notice.compiled_s is not None and notice.compiled_s > 0


def test_compile_notice_says_nothing_when_nothing_compiles():
    kernel = _fresh_kernel()
    kernel(1.0)  # compiled before the block
    stream = io.StringIO()
    with CompileNotice("demo", stream=stream, interval=0.01) as notice:
        kernel(2.0)
        time.sleep(0.03)
    assert stream.getvalue() == "" and notice.compiled_s is None


def test_compile_notice_writes_one_line_per_report_where_the_stream_is_no_terminal():
    stream = io.StringIO()
    with CompileNotice("demo", stream=stream, interval=0.01) as notice:
        _fresh_kernel()(1.0)
        time.sleep(0.05)
        notice.report()  # e.g. before the command prints a frame's row
        _fresh_kernel()(1.0)
        time.sleep(0.05)
    lines = stream.getvalue().splitlines()
    assert [line.split(" in ")[0] for line in lines] == [
        "compiling kernels for demo (first run, cached after)...", "compiled kernels for demo",
        "compiling kernels for demo (first run, cached after)...", "compiled kernels for demo"]


def test_warm_command_warms_the_named_pipelines(capsys):
    assert main(["warm", "bilateral"]) == 0
    assert capsys.readouterr().out.startswith("bilateral: ready in ")
    assert main(["warm", "bilateral", "nope"]) == 2  # unknown names fail before any warming
    captured = capsys.readouterr()
    assert captured.out == "" and "unknown pipeline 'nope'" in captured.err


def test_warm_command_with_jobs_warms_each_pipeline_in_a_process_of_its_own(capsys):
    assert main(["warm", "--jobs", "2", "bilateral", "statistical"]) == 0
    out = capsys.readouterr().out
    assert "bilateral: ready in" in out and "statistical: ready in" in out and "warmed 2 pipelines" in out
    assert main(["warm", "--jobs", "-1", "bilateral"]) == 2
