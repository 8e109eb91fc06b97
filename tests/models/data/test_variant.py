"""The variant choice and the crash isolation of rendering tests.

- `decide`: llvm only with LLVM >= MIN_LLVM, a probe render when the version is unknown, else scalar_rgb
  with a reason (mocked facts, no renderer).
- `choose_variant` on this machine's LLVM libraries, in subprocesses: scalar_rgb and one warning line
  when Dr.Jit would load LLVM 15 or 14 or none, and the probe catches LLVM 15's abort when the version
  is hidden from it.
- A native abort in a render subprocess fails one test with a clear message; the rest of the run goes on.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from models.data import variant
from models.data.variant import LLVM_CANDIDATES, MIN_LLVM, VARIANT_ENV, ProbeResult, decide, probe_variant
from tests.models.data.isolated import RenderCrashed, run_isolated

ROOT = Path(__file__).resolve().parents[3]
ALL = {"scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"}
LLVM_15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so"
LLVM_14 = "/usr/lib/x86_64-linux-gnu/libLLVM-14.so"
NO_LLVM = "/nonexistent/libLLVM.so"

SCALAR_RENDER = """
import numpy as np
from models.data.variant import choose_variant, load_mitsuba
from models.data import scenes
from models.data.render import RenderOptions, previous_of, render_frame
from service.frame import DIAGNOSTICS, LAYERS
print(choose_variant())
mi = load_mitsuba()
spec = scenes.get("fireflies")  # a numpy mesh, a sphere emitter, glossy BSDFs
opts = RenderOptions(12, 10, 2, 2, gbuffer_spp=1, emission_spp=1, ao_spp=2)
frame = render_frame(mi, spec, 0, opts, previous_of(mi, spec, 0, opts))
assert set(frame.layers) == set(LAYERS) - set(DIAGNOSTICS), sorted(frame.layers)
assert all(np.isfinite(v).all() for v in frame.layers.values())
assert (frame.gbuffer.shape >= 0).any()
print("ok")
"""


def _never(name: str) -> ProbeResult:
    raise AssertionError(f"probe({name}) called although the LLVM version is known")


def _probe(ok: bool, detail: str = ""):
    calls = []

    def probe(name: str) -> ProbeResult:
        calls.append(name)
        return ProbeResult(ok, detail)

    return probe, calls


@pytest.mark.parametrize("version", [(15, 0, 6), (16, 0, 0), (MIN_LLVM - 1, 1, 0)])
def test_falls_back_to_scalar_for_an_llvm_older_than_19(version):
    chosen, why = decide(ALL - {"cuda_ad_rgb"}, False, True, version, _never)
    assert chosen == "scalar_rgb"
    assert f"LLVM {'.'.join(map(str, version))}" in why and f">= {MIN_LLVM}" in why


def test_takes_llvm_for_llvm_19_and_cuda_first():
    assert decide(ALL, False, True, (19, 1, 7), _never) == ("llvm_ad_rgb", "")
    assert decide(ALL, True, True, (15, 0, 6), _never) == ("cuda_ad_rgb", "")


def test_falls_back_without_llvm_and_silently_without_an_llvm_build():
    chosen, why = decide(ALL, False, False, None, _never)
    assert chosen == "scalar_rgb" and "no usable LLVM" in why
    assert decide({"scalar_rgb"}, False, True, (19, 1, 0), _never) == ("scalar_rgb", "")


def test_probes_when_the_version_is_unknown():
    probe, calls = _probe(False, "the probe render was killed by SIGABRT: LLVM ERROR: Cannot select")
    chosen, why = decide(ALL, False, True, None, probe)
    assert calls == ["llvm_ad_rgb"] and chosen == "scalar_rgb" and "SIGABRT" in why
    probe, calls = _probe(True)
    assert decide(ALL, False, True, None, probe) == ("llvm_ad_rgb", "") and calls == ["llvm_ad_rgb"]


def test_probe_reports_a_native_abort(monkeypatch):
    monkeypatch.setattr(variant, "PROBE_CODE", "import sys, os\nprint('LLVM ERROR: boom', file=sys.stderr)\n"
                        "sys.stderr.flush()\nos.abort()\n")
    result = probe_variant("llvm_ad_rgb", timeout=60)
    assert not result.ok
    assert result.detail == "the probe render was killed by SIGABRT: LLVM ERROR: boom"


def _run(code: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", VARIANT_ENV)}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**clean, **(env or {})}, check=False, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return run


CHOOSE_TWICE = "from models.data.variant import choose_variant; print(choose_variant()); print(choose_variant())"


def _notices(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("Mitsuba renders with")]


@pytest.mark.parametrize("library, reason", [(LLVM_15, "Dr.Jit loads LLVM 15"), (LLVM_14, "no usable LLVM"),
                                             (NO_LLVM, "no usable LLVM")])
def test_choose_variant_on_this_machine_warns_once(library, reason):
    pytest.importorskip("mitsuba")
    if library != NO_LLVM and not Path(library).is_file():
        pytest.skip(f"{library} is not installed")
    run = _run(CHOOSE_TWICE, {"DRJIT_LIBLLVM_PATH": library})
    assert run.stdout.split() == ["scalar_rgb", "scalar_rgb"]
    notices = _notices(run.stderr)
    assert len(notices) == 1 and reason in notices[0], run.stderr  # cached: one check, one line


@pytest.mark.skipif(not Path(LLVM_15).is_file(), reason="needs LLVM 15, which makes the llvm variant abort")
def test_the_probe_catches_llvm_15s_abort_when_the_version_is_unknown():
    pytest.importorskip("mitsuba")
    code = ("from models.data import variant\nvariant.loaded_llvm_version = lambda dr: None\n" + CHOOSE_TWICE)
    run = _run(code, {"DRJIT_LIBLLVM_PATH": LLVM_15})
    assert run.stdout.split() == ["scalar_rgb", "scalar_rgb"]
    [notice] = _notices(run.stderr)
    assert "killed by SIGABRT" in notice and "LLVM ERROR" in notice


def test_forcing_a_variant_skips_the_checks():
    run = _run(CHOOSE_TWICE, {VARIANT_ENV: "llvm_ad_rgb", "DRJIT_LIBLLVM_PATH": NO_LLVM})
    assert run.stdout.split() == ["llvm_ad_rgb", "llvm_ad_rgb"] and not _notices(run.stderr)


def test_falls_back_to_scalar_without_llvm_and_renders_every_layer():
    pytest.importorskip("mitsuba")
    out = _run(SCALAR_RENDER, {"DRJIT_LIBLLVM_PATH": NO_LLVM}).stdout.split()
    assert out[0] == "scalar_rgb" and out[-1].endswith("ok")  # (Mitsuba warns about Python integrators between)


@pytest.mark.skipif(not any(Path(p).is_file() for p in LLVM_CANDIDATES), reason="LLVM 19 is not installed")
def test_chooses_llvm_when_llvm_19_is_installed():
    pytest.importorskip("mitsuba")
    assert _run("from models.data.variant import choose_variant; print(choose_variant())").stdout.split() == [
        "llvm_ad_rgb"]


def test_a_native_abort_in_a_render_subprocess_is_one_clear_failure():
    with pytest.raises(RenderCrashed, match=r"render subprocess posix\.abort was killed by SIGABRT"):
        run_isolated(os.abort)
    assert run_isolated(sum, [1, 2, 3]) == 6


SUITE = '''
import os
from tests.models.data.isolated import render_or_fail

def test_renderer_aborts():
    render_or_fail(os.abort)

def test_after_the_abort():
    assert render_or_fail(abs, -2) == 2
'''


def test_the_rest_of_the_suite_runs_after_a_render_abort(tmp_path):
    suite = tmp_path / "test_abort_suite.py"
    suite.write_text(textwrap.dedent(SUITE))
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(ROOT),
                          str(suite)], capture_output=True, text=True, cwd=ROOT, check=False, timeout=300)
    assert run.returncode == 1, run.stdout[-3000:]  # tests failed; pytest itself was not aborted
    assert "1 failed, 1 passed" in run.stdout, run.stdout[-3000:]
    assert "render subprocess posix.abort was killed by SIGABRT" in run.stdout, run.stdout[-3000:]
