"""The variant choice: llvm where LLVM loads, scalar_rgb otherwise, and the scalar path renders every layer."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from models.data.variant import LLVM_CANDIDATES, VARIANT_ENV

pytest.importorskip("mitsuba")

ROOT = Path(__file__).resolve().parents[3]

SCALAR_RENDER = """
import numpy as np
from models.data.variant import choose_variant, load_mitsuba
from models.data import scenes
from models.data.render import RenderOptions, previous_of, render_frame
from service.frame import LAYERS
print(choose_variant())
mi = load_mitsuba()
spec = scenes.get("fireflies")  # a numpy mesh, a sphere emitter, glossy BSDFs
opts = RenderOptions(12, 10, 2, 2, gbuffer_spp=1, emission_spp=1, ao_spp=2)
frame = render_frame(mi, spec, 0, opts, previous_of(mi, spec, 0, opts))
assert set(frame.layers) == set(LAYERS), sorted(frame.layers)
assert all(np.isfinite(v).all() for v in frame.layers.values())
assert (frame.gbuffer.shape >= 0).any()
print("ok")
"""


def _run(code: str, **env: str) -> list[str]:
    clean = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", VARIANT_ENV)}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**clean, **env}, check=False, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout.split()


def test_falls_back_to_scalar_without_llvm_and_renders_every_layer():
    out = _run(SCALAR_RENDER, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    assert out[0] == "scalar_rgb" and out[-1].endswith("ok")  # (Mitsuba warns about Python integrators between)


@pytest.mark.skipif(not any(Path(p).is_file() for p in LLVM_CANDIDATES), reason="LLVM 19 is not installed")
def test_chooses_llvm_when_llvm_19_is_installed():
    out = _run("from models.data.variant import choose_variant; print(choose_variant())")
    assert out == ["llvm_ad_rgb"]
