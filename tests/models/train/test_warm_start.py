"""The crossreg warm start's cached pilots are those the pipeline computes, with either kind of pilots."""

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from models.train.warm_start import _with_pilots
from service.frame import Frame
from service.layout import CROSSREG_INPUTS, channel_slices
from service.pipelines.crossreg import next_history, prepare_frame


@pytest.mark.parametrize("averaged", [False, True])
def test_cached_pilots_are_the_pipelines(averaged):
    frames = [Frame.from_buffers(x) for x in synthetic_sequence(20, 28, 4, spp=4, seed=3)]
    cached = _with_pilots("s", frames, {}, averaged=averaged)
    s = channel_slices(CROSSREG_INPUTS)
    history = None
    for frame, (pilot_a, pilot_b) in zip(cached.frames, cached.pilots, strict=True):
        prepared = prepare_frame(frame, history, average=averaged)
        np.testing.assert_array_equal(prepared.planes[s["pilotA"]], pilot_a)
        np.testing.assert_array_equal(prepared.planes[s["pilotB"]], pilot_b)
        history = next_history(frame, prepared, prepared.planes[s["previous"]])
    assert averaged == (history.halves is not None)
