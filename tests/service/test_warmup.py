import numpy as np
import pytest

from service import pipelines
from service.frame import LAYERS
from service.warmup import WARMUP_SIZE, warm_up, warmup_frame


def test_warmup_frame_has_every_layer_valid():
    frame = warmup_frame(*WARMUP_SIZE)
    assert [name for name in LAYERS if name not in frame] == ["reference"]
    np.testing.assert_allclose(np.linalg.norm(frame["normal"], axis=-1), 1.0, rtol=1e-5)
    assert (frame["sampleCount"] > 0).all() and not frame["emission"].any()


@pytest.mark.parametrize("name", pipelines.names())
def test_every_pipeline_warms_up_on_the_generated_frames(name):
    warm_up(pipelines.get(name))  # raises what the pipeline raises
