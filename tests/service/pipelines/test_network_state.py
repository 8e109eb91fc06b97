"""The recurrent network pipelines (`rae`, `kpn`): a non-finite network output resets the recurrent state, the
frame is refused, and the sequence goes on with its next frame."""

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from service import pipelines
from service.exr import read_sequence
from service.frame import Frame

# name -> whether a sequence state holds no recurrent state (as at a sequence's first frame)
EMPTY = {"rae": lambda state: state.hidden == [], "kpn": lambda state: state.previous is None}


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [frame for _path, frame in read_sequence(SAMPLE_DIRS[0])][:3]


@pytest.mark.parametrize("name", sorted(EMPTY))
def test_a_non_finite_network_output_resets_the_state_and_the_sequence_goes_on(frames, monkeypatch, name):
    pipeline = pipelines.get(name)
    state = pipeline.start(120, 120)
    _, state = pipeline.step(frames[0], state)
    assert not EMPTY[name](state)
    model = pipeline.model()
    real = model.run
    monkeypatch.setattr(model, "run", lambda feeds: {k: v * np.nan for k, v in real(feeds).items()})
    with pytest.raises(FloatingPointError, match="recurrent state was reset"):
        pipeline.step(frames[1], state)
    assert EMPTY[name](state)
    monkeypatch.setattr(model, "run", real)
    out, state = pipeline.step(frames[2], state)
    assert np.isfinite(out["color"]).all() and not EMPTY[name](state)
