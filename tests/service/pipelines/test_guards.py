"""The step's hard-case guards (Pipeline.step, `Pipeline.guards`): a visible light without an emission layer
comes out exactly as it went in and does not leak into its neighbours, and a sky seen directly comes out as it
came, for every pipeline; anchors run without the guards."""

import numpy as np
import pytest

from bench.methods import anchor_method
from service import pipelines
from service.frame import Frame, FrameError
from service.pipelines.base import Pipeline, with_exact_emission
from service.stages.background import FILTER_REACH
from service.stages.exact import exact_mask

LIGHT = (slice(10, 13), slice(18, 21))  # 3x3 pixels of a directly visible light
RING = (slice(8, 15), slice(16, 23))  # the light and two pixels around it


def _with_light(layers: dict[str, np.ndarray]) -> Frame:
    """A synthetic frame with a light of radiance 1e3 whose halves agree (exact), no emission layer."""
    buffers = {k: v.copy() for k, v in layers.items() if k not in ("emission", "reference")}
    for name in ("color", "colorA", "colorB"):
        buffers[name][LIGHT] = 1000.0
    return Frame.from_buffers(buffers)


@pytest.mark.parametrize("name", pipelines.names())
def test_a_light_without_emission_layer_stays_exact_and_in_place(name, tiny_layers):
    pipeline = pipelines.get(name)
    state = pipeline.start(24, 40)
    for layers in tiny_layers[:2]:
        frame = _with_light(layers)
        out, state = pipeline.step(frame, state)
    color = out["color"]
    np.testing.assert_array_equal(color[LIGHT], frame["color"][LIGHT])
    ring = np.zeros(color.shape[:2], bool)
    ring[RING] = True
    ring[LIGHT] = False
    assert color[ring].max() < 50.0  # no glow, no blown-out block around the light (surround ~1)
    assert color[ring].min() >= 0.0  # no black ring


@pytest.mark.parametrize("emitters", [False, True], ids=["no-emission", "emission-of-emitters-only"])
@pytest.mark.parametrize("name", pipelines.names())
def test_a_sky_seen_directly_comes_out_as_it_came(name, emitters, tiny_layers):
    """Nothing hit (zero normal), halves that differ a little (the pixel filter's jitter over a textured sky of
    radiance ~1e2), and no emission layer or one of the emitters alone (Blender's Emit without Env): every
    pipeline returns those pixels beyond the pixel filter's reach of a surface as they came, its neighbours
    denoised."""
    pipeline = pipelines.get(name)
    state = pipeline.start(24, 40)
    rng = np.random.default_rng(5)
    sky = (slice(0, 6), slice(0, 40))
    for layers in tiny_layers[:2]:
        buffers = {k: v.copy() for k, v in layers.items() if k not in ("emission", "reference")}
        texture = (100.0 * (1.0 + rng.random((6, 40, 1)))).astype(np.float32)
        jitter = (rng.standard_normal((6, 40, 3)) * 0.5).astype(np.float32)
        buffers["colorA"][sky], buffers["colorB"][sky] = texture + jitter, texture - jitter
        buffers["color"][sky] = texture
        buffers["normal"][sky] = 0.0
        if emitters:
            buffers["emission"] = np.zeros_like(buffers["color"])
            for name_ in ("color", "colorA", "colorB", "emission"):
                buffers[name_][LIGHT] = 1000.0
        frame = Frame.from_buffers(buffers)
        out, state = pipeline.step(frame, state)
    interior = (slice(0, 6 - FILTER_REACH), slice(0, 40))  # beyond the pixel filter's reach of the surfaces
    np.testing.assert_array_equal(out["color"][interior], frame["color"][interior])
    below = out["color"][8:]
    if emitters:
        np.testing.assert_array_equal(out["color"][LIGHT], frame["color"][LIGHT])
        below = np.where(np.isin(np.arange(8, 24), range(10, 13))[:, None, None], 0.0, below)
    assert np.isfinite(below).all() and below.max() < 50.0  # the sky's radiance did not reach the surfaces


@pytest.mark.parametrize("name", pipelines.names())
def test_no_black_ring_where_the_emission_pass_saw_other_coverage(name, tiny_layers):
    """A light of radiance 1e3 crossed by a dark bar one pixel wide, its emission layer from another pass than
    the colour's (an edge pixel's coverage differs, as with our renderer's 16-spp emission pass), no halves
    unless the pipeline needs them: nothing comes out below 0 (flr, bmfr, flnr and svgf did, down to -0.33)."""
    pipeline = pipelines.get(name)
    state = pipeline.start(24, 40)
    light, bar = (slice(8, 16), slice(14, 26)), (slice(8, 16), 19)
    for layers in tiny_layers[:2]:
        halves = ("colorA", "colorB") if "colorA" in pipeline.requires else ()
        dropped = ("reference",) if halves else ("reference", "colorA", "colorB")
        buffers = {k: v.copy() for k, v in layers.items() if k not in dropped}
        buffers["emission"] = np.zeros_like(buffers["color"])
        for name_ in ("color", "emission", *halves):
            buffers[name_][light] = 1000.0
            buffers[name_][bar] = 0.0
        buffers["color"][9, 15], buffers["emission"][9, 16] = 400.0, 500.0
        out, state = pipeline.step(Frame.from_buffers(buffers), state)
    assert out["color"].min() >= 0.0


def test_exact_pixels_become_emission_and_a_renderers_emission_decides(tiny_layers):
    frame = _with_light(tiny_layers[0])
    emission = with_exact_emission(frame)["emission"]
    assert (emission[LIGHT] == 1000.0).all()
    mask = exact_mask(frame["colorA"], frame["colorB"])  # the light and the synthetic scene's noise-free emitter
    np.testing.assert_array_equal(emission.any(axis=-1), mask)
    assert mask.sum() < 0.2 * mask.size
    given = np.zeros_like(frame["color"])
    given[LIGHT] = 1000.0
    given[10, 18] = 400.0  # the renderer says this pixel is only partly the light: its halves agree by chance
    with_layer = frame.replace(emission=given)
    assert with_exact_emission(with_layer) is with_layer
    pipeline = pipelines.get("crossregression")
    out, _ = pipeline.step(with_layer, pipeline.start(24, 40))
    assert (out["color"][11, 19] == 1000.0).all()  # exact and all emission: as it came in
    assert out["color"][10, 18].max() < 1000.0  # the denoised residual plus the renderer's 400


class _Brighter(Pipeline):
    """A test double that adds 100 to every pixel: far outside the noise of the halves."""

    name, summary, requires = "brighter", "test double", ("color",)

    def denoise(self, frame, state):
        return {"color": frame["color"] + 100.0}, state


def test_guards_clip_to_the_noise_and_anchors_run_without_them(tiny_layers):
    noisy = anchor_method("noisy").make()
    # auto leaves the guards to the candidates it steps
    assert not noisy.guards and all(pipelines.get(n).guards for n in pipelines.names() if n != pipelines.AUTO)
    frame = _with_light(tiny_layers[0])
    guarded, unguarded = _Brighter(), _Brighter()
    unguarded.guards = False
    free, _ = unguarded.step(frame, unguarded.start(24, 40))
    np.testing.assert_array_equal(free["color"], frame["color"] + 100.0)
    clipped, _ = guarded.step(frame, guarded.start(24, 40))
    assert clipped["color"].max() < 1000.0 + 1e-3 and (clipped["color"] < frame["color"] + 100.0).all()
    np.testing.assert_array_equal(clipped["color"][LIGHT], frame["color"][LIGHT])


def test_the_noisy_anchor_is_the_input_even_at_an_emitters_edge(tiny_layers):
    """The emission split clips the remainder at a pixel with emission whose colour missed the light; the
    anchor takes no split."""
    frame = _with_light(tiny_layers[0])
    emission = np.zeros_like(frame["color"])
    emission[LIGHT] = 1000.0
    emission[9, 19] = 300.0  # a light's edge the colour's samples missed
    frame = frame.replace(emission=emission)
    noisy = anchor_method("noisy").make()
    out, _ = noisy.step(frame, noisy.start(24, 40))
    np.testing.assert_array_equal(out["color"], frame["color"])


@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan])
def test_a_non_finite_output_is_caught_before_the_clamp(value, tiny_layers):
    class Infinite(_Brighter):
        def denoise(self, frame, state):
            return {"color": np.full_like(frame["color"], value)}, state

    pipeline = Infinite()
    with pytest.raises(FloatingPointError, match="non-finite 'color'"):
        pipeline.step(_with_light(tiny_layers[0]), pipeline.start(24, 40))


def test_a_temporal_pipeline_blends_with_the_accumulated_input(tiny_layers):
    """A temporal pipeline's blend takes the input accumulated over the sequence (its state's `input_history`,
    which reads `motion` and `depth`); a pipeline that is not temporal keeps none; a frame without motion starts
    it again, one without halves or one refused forgets it."""
    class Temporal(_Brighter):
        temporal = True

    states = {}
    for pipeline, kept in ((Temporal(), True), (_Brighter(), False)):
        assert ("motion" in pipeline.reads()) == kept
        state = pipeline.start(24, 40)
        for layers in tiny_layers:
            _, state = pipeline.step(Frame.from_buffers(layers), state)
        assert (state.input_history.buffer is not None) == kept
        states[kept] = pipeline, state
    pipeline, state = states[True]
    assert state.input_history.buffer[..., 3].max() == 3.0  # frames in it: the static pixels have all three
    no_motion = {k: v for k, v in tiny_layers[0].items() if k != "motion"}
    pipeline.step(Frame.from_buffers(no_motion), state)
    assert state.input_history.buffer[..., 3].max() == 1.0  # a new start
    no_halves = {k: v for k, v in tiny_layers[1].items() if k not in ("colorA", "colorB")}
    pipeline.step(Frame.from_buffers(no_halves), state)
    assert state.input_history.buffer is None
    pipeline.step(Frame.from_buffers(tiny_layers[0]), state)
    with pytest.raises(FrameError):  # a refused frame: the next one's motion points to it
        pipeline.step(Frame.from_buffers({k: v[:12] for k, v in tiny_layers[1].items()}), state)
    assert state.input_history.buffer is None


def test_the_step_clamps_per_surface_with_the_frames_normal_and_depth():
    """A box's unlit side, one pixel wide, beside a noisy lit floor (service/stages/noise_clamp.py): the step
    gives the clamp the frame's normal and depth, so a filter's bleed onto it comes out black, and every guarded
    pipeline reads depth."""
    class Bleed(Pipeline):
        name, summary, requires = "bleed", "test double", ("color",)

        def denoise(self, frame, state):
            out = frame["color"].copy()
            out[:, 6] = 0.1
            return {"color": out}, state

    rng = np.random.default_rng(0)
    shape = (12, 12, 3)
    a = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    b = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    a[:, 6:] = b[:, 6:] = 0.0
    normal = np.zeros(shape, np.float32)
    normal[:, :6, 2] = 1.0
    normal[:, 6, 0] = -1.0
    depth = np.full((12, 12, 1), 1e4, np.float32)
    depth[:, :6], depth[:, 6] = 4.0, 3.0
    frame = Frame.from_buffers({"color": (a + b) / 2, "colorA": a, "colorB": b, "normal": normal, "depth": depth})
    pipeline = Bleed()
    out, _ = pipeline.step(frame, pipeline.start(12, 12))
    assert (out["color"][:, 6] == 0.0).all()
    assert "depth" in pipeline.reads() and "depth" in pipelines.pipeline_class("bilateral").reads()
