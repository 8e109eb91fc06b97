"""Shared fixtures: small synthetic frames and sequences with every layer and a reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence, write_synthetic_sequence
from service.frame import Frame
from service.process import configure

configure()  # the test session is an entry point: the kernels' versioned cache folder, OpenMP waiting


@pytest.fixture(scope="session")
def tiny_layers() -> list[dict[str, np.ndarray]]:
    """Three 24x40 frames (H x W) of the synthetic scene, every layer."""
    return synthetic_sequence(height=24, width=40, frames=3, spp=8, seed=3)


@pytest.fixture()
def tiny_frame(tiny_layers) -> Frame:
    return Frame.from_buffers(tiny_layers[0])


@pytest.fixture()
def tiny_sequence_dir(tmp_path: Path) -> Path:
    """A folder with 3 synthetic 40x24 frames and sequence.json."""
    folder = tmp_path / "seq"
    write_synthetic_sequence(folder, height=24, width=40, frames=3, spp=8, seed=3)
    return folder
