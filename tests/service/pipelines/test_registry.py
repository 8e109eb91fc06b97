import numpy as np
import pytest

from service import pipelines
from service.frame import Frame, FrameError
from service.pipelines import UnknownPipelineError, tiled


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


@pytest.mark.parametrize("name", [n for n in pipelines.names() if pipelines.pipeline_class(n).temporal])
def test_after_a_refused_frame_a_sequence_starts_again(name, tiny_layers):
    """A refused frame leaves no history behind (the next frame's motion points to it; a stage that failed may
    have written part of it): the frame after it comes out as the first frame of a new sequence."""
    pipeline = pipelines.get(name)
    frames = [Frame.from_buffers(layers) for layers in tiny_layers]
    state = pipeline.start(24, 40)
    _, state = pipeline.step(frames[0], state)
    _, state = pipeline.step(frames[1], state)
    with pytest.raises(FrameError, match="required by pipeline"):
        pipeline.step(Frame.from_buffers({"depth": np.ones((24, 40, 1))}), state)
    after, _ = pipeline.step(frames[2], state)
    fresh, _ = pipeline.step(frames[2], pipeline.start(24, 40))
    np.testing.assert_array_equal(after["color"], fresh["color"])
    continued, _ = pipeline.step(frames[2], pipeline.step(frames[1], pipeline.start(24, 40))[1])
    assert not np.array_equal(continued["color"], fresh["color"])  # the history would have shown


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


@pytest.mark.parametrize("name", [n for n in pipelines.names() if n != "statistical"])  # its statistics hold emission
def test_emission_split_matches_denoising_the_emission_free_frame(name, tiny_layers, monkeypatch):
    """Every radiance layer a pipeline reads loses the emission before denoising: the output on
    radiance + emission equals the output on radiance alone, plus the emission. `auto`'s blend weights come
    from an estimate normalised by the radiance with its emission (as relL2 is), so they may differ between
    the two frames: its blend is fixed here, and the split is its candidates'."""
    if name == pipelines.AUTO:
        def halves_of_the_first_two(covariance, *args):
            weights = np.zeros(covariance.shape[1:])
            weights[:2] = 0.5
            return weights, (0, 1)

        monkeypatch.setattr(tiled, "choose", halves_of_the_first_two)
    layers = {k: v.copy() for k, v in tiny_layers[0].items() if k not in ("reference", "emission")}
    height, width = layers["color"].shape[:2]
    emission = np.zeros((height, width, 3), np.float32)
    emission[5:9, 10:16] = 40.0  # an emitter seen directly
    for k in ("color", "colorA", "colorB"):  # flat around its edge: within the split's clip (test_emission)
        layers[k][4:10, 9:17] = layers[k][4, 9].copy()
    with_emission = {k: v + emission if k in ("color", "colorA", "colorB") else v for k, v in layers.items()}
    pipeline = pipelines.get(name)
    # a zero emission layer, so that the step treats both frames alike (no exact pixels taken as emission)
    no_emission = {**layers, "emission": np.zeros_like(emission)}
    plain, _ = pipeline.step(Frame.from_buffers(no_emission), pipeline.start(height, width))
    split, _ = pipeline.step(Frame.from_buffers({**with_emission, "emission": emission}), pipeline.start(height, width))
    # the emitter's own pixels: the step's guards leave them as the denoiser made them with the emission
    # known (noise clamp, noise blend), and blend them without; everywhere else the outputs agree
    emitted = (emission != 0).any(axis=-1)
    np.testing.assert_allclose(split["color"][~emitted], (plain["color"] + emission)[~emitted], rtol=1e-4, atol=1e-4)
    assert np.isfinite(split["color"]).all() and (split["color"][emitted] >= 0.5 * emission[emitted]).all()


def test_denoise_sees_emission_free_colour_and_declared_halves():
    """`color` always loses the emission (every pipeline may read it, e.g. for a range clamp); the half
    buffers do where the pipeline declares them."""
    from service.pipelines.base import Pipeline

    seen = {}

    class Probe(Pipeline):
        name, summary, requires, optional = "probe", "records its input", ("colorA",), ("emission",)

        def denoise(self, frame, state):
            seen.update({k: frame[k] for k in ("color", "colorA", "colorB")})
            return {"color": frame["color"]}, state

    one = np.ones((4, 5, 3), np.float32)
    frame = Frame.from_buffers({"color": 3 * one, "colorA": 3 * one, "colorB": 3 * one, "emission": 2 * one})
    Probe().step(frame, Probe().start(4, 5))
    np.testing.assert_array_equal(seen["color"], one)
    np.testing.assert_array_equal(seen["colorA"], one)
    np.testing.assert_array_equal(seen["colorB"], 3 * one)  # not declared: left as it is


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


@pytest.mark.parametrize("with_emission", [False, True])
def test_a_non_finite_output_is_refused(with_emission):
    """The step's guard, whether the emission pass or the plain scan looks at the colour."""
    from service.pipelines.base import Pipeline

    class Broken(Pipeline):
        name, summary, requires, optional = "broken", "returns a NaN", (), ("emission",)

        def denoise(self, frame, state):
            color = frame["color"].copy()
            color[3, 4, 2] = np.nan
            return {"color": color}, state

    one = np.ones((4, 5, 3), np.float32)
    frame = Frame.from_buffers({"color": one, **({"emission": one} if with_emission else {})})
    with pytest.raises(FloatingPointError, match="pipeline 'broken' produced non-finite 'color'"):
        Broken().step(frame, Broken().start(4, 5))
