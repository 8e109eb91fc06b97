"""The bundled sample sequence(s): complete, within the size budget, physically plausible; and the package
that names them imports without mitsuba."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from models.data.evaluate import sequence_report
from service.exr import list_sequence, read_frame, read_metadata
from service.frame import DIAGNOSTICS, LAYERS

SAMPLE_BUDGET_BYTES = 5_000_000  # issue 7: at most 5 MB of bundled sample data in all


def test_sample_folders_exist_and_fit_the_budget():
    assert SAMPLE_DIRS and all(d.is_dir() for d in SAMPLE_DIRS)
    total = sum(f.stat().st_size for d in SAMPLE_DIRS for f in d.iterdir())
    assert total <= SAMPLE_BUDGET_BYTES


@pytest.mark.parametrize("folder", SAMPLE_DIRS, ids=lambda p: p.name)
def test_sample_frames_carry_every_layer(folder):
    files = list_sequence(folder)
    meta = read_metadata(folder)
    assert len(files) == len(meta["frames"]) == 8
    for path in files:
        frame = read_frame(path)
        assert set(frame.buffers) == set(LAYERS) - set(DIAGNOSTICS) and frame.nonfinite_total == 0
        assert (frame.width, frame.height) == tuple(meta["size"]) and min(meta["size"]) >= 96
        assert np.all(frame["sampleCount"] == meta["spp"])


@pytest.mark.parametrize("folder", SAMPLE_DIRS, ids=lambda p: p.name)
def test_sample_is_noisy_and_its_motion_vectors_warp(folder):
    report = sequence_report(folder)
    assert report["noisy_rel_l2"] > 0.01  # a denoiser has work to do
    assert report["motion"] < 0.5 * report["static"]  # warping explains most frame-to-frame change
    assert report["dual_disoccluded"] < report["motion_disoccluded"]  # dual vectors fetch background


def test_package_imports_without_mitsuba():
    code = (
        "import importlib.abc, sys\n"
        "class Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('mitsuba', 'drjit'):\n"
        "            raise ImportError('blocked: ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import models.data, models.data.scenes, models.data.motion, models.data.evaluate\n"
        "import models.data.render, models.data.sequence, models.data.dataset, models.data.__main__\n"
        "print(len(models.data.SAMPLE_DIRS))\n"
    )
    root = Path(__file__).resolve().parents[3]
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd=root)
    assert run.returncode == 0, run.stderr
