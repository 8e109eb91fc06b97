import numpy as np
import pytest

from service import pipelines
from service.frame import Frame, FrameError
from service.pipelines import UnknownPipelineError


def test_every_pipeline_declares_its_contract():
    for info in pipelines.describe():
        assert info["summary"] and isinstance(info["temporal"], bool)
        assert set(info["requires"]).isdisjoint(info["optional"])
    assert pipelines.DEFAULT in pipelines.names()


def test_unknown_pipeline_lists_available():
    with pytest.raises(UnknownPipelineError, match="unknown pipeline 'nope'; available: .*bilateral"):
        pipelines.get("nope")


def test_unknown_option_is_refused():
    with pytest.raises(ValueError, match="pipeline 'bilateral' has no option 'radios'"):
        pipelines.get("bilateral", radios=3)


def test_auto_picks_a_pipeline_the_frame_can_feed():
    assert pipelines.auto({"color"}) == "bilateral"
    with pytest.raises(UnknownPipelineError):
        pipelines.auto({"depth"})


@pytest.mark.parametrize("name", pipelines.names())
def test_missing_required_layer_is_refused_before_work(name):
    pipeline = pipelines.get(name)
    state = pipeline.start(4, 4)
    frame = Frame.from_buffers({"depth": np.ones((4, 4, 1))})
    with pytest.raises(FrameError, match=f"required by pipeline '{name}'"):
        pipeline.step(frame, state)
    assert state.frame_index == 0


@pytest.mark.parametrize("name", pipelines.names())
def test_frame_of_another_size_is_refused(name, tiny_layers):
    pipeline = pipelines.get(name)
    state = pipeline.start(10, 10)
    with pytest.raises(FrameError, match="frame is 40x24 but the sequence is 10x10"):
        pipeline.step(Frame.from_buffers(tiny_layers[0]), state)


@pytest.mark.parametrize("name", pipelines.names())
def test_every_pipeline_denoises_the_synthetic_sequence(name, tiny_layers):
    from service.metrics import rel_l2

    pipeline = pipelines.get(name)
    state = pipeline.start(24, 40)
    noisy, denoised = [], []
    for layers in tiny_layers:
        frame = Frame.from_buffers(layers)
        out, state = pipeline.step(frame, state)
        assert out["color"].shape == (24, 40, 3) and out["color"].dtype == np.float32
        assert np.isfinite(out["color"]).all()
        noisy.append(rel_l2(frame["color"], layers["reference"]))
        denoised.append(rel_l2(out["color"], layers["reference"]))
    assert state.frame_index == len(tiny_layers)
    assert np.mean(denoised) < 0.5 * np.mean(noisy)


def test_emission_is_split_off_and_added_back_exactly():
    """With only emission (no other radiance), any filter must return the emission untouched."""
    rng = np.random.default_rng(0)
    emission = np.where(rng.random((12, 12, 1)) > 0.8, 50.0, 0.0).astype(np.float32) * np.ones(3, np.float32)
    frame = Frame.from_buffers({"color": emission, "emission": emission})
    pipeline = pipelines.get("bilateral")
    out, _ = pipeline.step(frame, pipeline.start(12, 12))
    np.testing.assert_allclose(out["color"], emission, atol=1e-5)


def test_input_repairs_are_reported_on_the_output():
    color = np.ones((5, 5, 3), np.float32)
    color[2, 2] = np.nan
    frame = Frame.from_buffers({"color": color})
    pipeline = pipelines.get("bilateral")
    out, _ = pipeline.step(frame, pipeline.start(5, 5))
    assert out.nonfinite == {"color": 3} and np.isfinite(out["color"]).all()


def test_start_refuses_empty_size():
    with pytest.raises(ValueError, match="at least 1x1"):
        pipelines.get("bilateral").start(0, 5)
