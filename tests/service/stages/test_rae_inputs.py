"""The recurrent autoencoder's input planes and output transform: hand-computed values, scale-free depth,
the round trip, and parity with the torch side that training feeds the network with."""

import numpy as np
import pytest

from service.layout import RAE_INPUTS, channel_slices
from service.stages.albedo import ALBEDO_EPS, demodulate, remodulate
from service.stages.rae_inputs import (
    DEPTH_CLIP,
    RADIANCE,
    ROUGHNESS_ABSENT,
    demodulated,
    guide_planes,
    lighting_from_output,
    rae_planes,
)
from tests.tolerances import TWIN_ATOL


def _frame(h=6, w=7, seed=0):
    rng = np.random.default_rng(seed)
    color = rng.gamma(1.0, 2.0, (h, w, 3)).astype(np.float32)
    albedo = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    normal = rng.standard_normal((h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = rng.uniform(1, 5, (h, w, 1)).astype(np.float32)
    rough = rng.uniform(0, 1, (h, w, 1)).astype(np.float32)
    return color, albedo, normal, depth, rough


def test_planes_follow_the_layout_with_hand_computed_values():
    color, albedo, normal, depth, rough = _frame()
    color[0, 0] = (-1.0, 0.0, 3.0)  # negative radiance reads as 0
    albedo[0, 0] = (0.0, 0.5, 0.99)
    depth[:] = 2.0
    depth[0, 0] = 1e10  # a miss: clipped
    planes = rae_planes(color, albedo, normal, depth, rough)
    where = channel_slices(RAE_INPUTS)
    assert planes.shape == (8, 6, 7) and planes.dtype == np.float32
    np.testing.assert_allclose(planes[where["radiance"], 0, 0],
                               [0.0, 0.0, np.log1p(3.0 / (0.99 + ALBEDO_EPS))], rtol=1e-6)
    np.testing.assert_array_equal(planes[where["normal"]], normal.transpose(2, 0, 1))
    assert planes[where["depth"], 1, 1] == pytest.approx(np.log1p(1.0))  # median 2: relative 1
    assert planes[where["depth"], 0, 0] == pytest.approx(np.log1p(DEPTH_CLIP))
    np.testing.assert_array_equal(planes[where["roughness"]][0], rough[..., 0])
    assert (rae_planes(color, albedo, normal, depth, None)[where["roughness"]] == ROUGHNESS_ABSENT).all()


def test_roughness_is_held_to_its_range():
    """The frame contract does not bound `roughness`; a network fed 3e38 made non-finite output (kpn, rae)."""
    color, albedo, normal, depth, rough = _frame()
    rough[0, :3, 0] = (3e38, -3e38, 1.5)
    plane = guide_planes(normal, depth, rough)[channel_slices(RAE_INPUTS)["roughness"].start - RADIANCE.stop]
    assert tuple(plane[0, :3]) == (1.0, 0.0, 1.0) and (plane[1:] == rough[1:, :, 0]).all()


def test_depth_in_millimetres_or_metres_gives_the_same_planes():
    color, albedo, normal, depth, rough = _frame(seed=1)
    np.testing.assert_allclose(guide_planes(normal, depth, rough), guide_planes(normal, depth * 1000, rough),
                               rtol=1e-6)


def test_sky_does_not_move_the_depth_scale():
    """Misses (zero normal, any large depth) stay out of the median: the planes of the surfaces do not
    change when most of the frame turns to sky."""
    color, albedo, normal, depth, rough = _frame(h=16, w=16, seed=4)
    some_sky, most_sky = (normal.copy(), depth.copy()), (normal.copy(), depth.copy())
    some_sky[0][:4], some_sky[1][:4] = 0.0, 1e10
    most_sky[0][:12], most_sky[1][:12] = 0.0, 1e10
    a = guide_planes(*some_sky, rough)
    b = guide_planes(*most_sky, rough)
    surface = slice(12, 16)
    scale_a = np.median(depth[4::4, ::4])  # the hits of the stride-4 subsample
    scale_b = np.median(depth[12::4, ::4])
    np.testing.assert_allclose(a[3, surface], np.log1p(depth[surface, :, 0] / scale_a), rtol=1e-5)
    np.testing.assert_allclose(b[3, surface], np.log1p(depth[surface, :, 0] / scale_b), rtol=1e-5)
    assert (b[3, :12] == np.float32(np.log1p(DEPTH_CLIP))).all()


def test_output_transform_inverts_the_input_transform():
    color, albedo, *_ = _frame(seed=2)
    planes = np.log1p(demodulated(color, albedo)).transpose(2, 0, 1)
    np.testing.assert_allclose(remodulate(lighting_from_output(planes), albedo), color, rtol=1e-5)


def test_output_is_finite_and_non_negative_for_any_network_output():
    albedo = np.full((2, 2, 3), 0.5, np.float32)
    wild = np.array([-1e30, -1.0, 1e3, 3e38], np.float32).reshape(1, 2, 2).repeat(3, axis=0)
    out = remodulate(lighting_from_output(wild), albedo)
    assert np.isfinite(out).all() and (out >= 0).all()


def test_background_planes_are_those_of_a_black_colour():
    color, albedo, normal, depth, rough = _frame(h=9, w=11, seed=5)
    background = np.zeros((9, 11), bool)
    background[:3], background[5, 7] = True, True
    np.testing.assert_array_equal(rae_planes(color, albedo, normal, depth, rough, background=background),
                                  rae_planes(np.where(background[..., None], np.float32(0), color), albedo, normal,
                                             depth, rough))


@pytest.mark.parametrize(("size", "roughness"), [((13, 17), True), ((1, 1), True), ((37, 9), False)])
def test_torch_training_inputs_match_the_serving_planes(size, roughness):
    """What training feeds the network (RaeRecipe.inputs: torch's clamp and log1p of the demodulated radiance,
    then the `guide_planes` the data set stores) against what serving feeds it, on random data of odd sizes.
    The radiance goes in unclamped, negative values included, so the torch clamp is held to numpy's too."""
    torch = pytest.importorskip("torch")
    from models.train.rae import RaeRecipe

    rng = np.random.default_rng(size[0])
    color, albedo, normal, depth, rough = _frame(*size, seed=size[1])
    color = (rng.standard_normal(color.shape) * 4).astype(np.float32)  # a third negative
    albedo[rng.uniform(size=albedo.shape) < 0.2] = 0.0
    rough = rough if roughness else None
    served = rae_planes(color, albedo, normal, depth, rough)
    noisy = torch.from_numpy(demodulate(color, albedo).transpose(2, 0, 1).copy())  # not clamped here
    guides = torch.from_numpy(guide_planes(normal, depth, rough))
    trained = RaeRecipe.inputs(noisy[None], guides[None])[0].numpy()
    assert trained.shape == served.shape == (8, *size)
    np.testing.assert_allclose(trained, served, rtol=1e-6, atol=TWIN_ATOL)
    np.testing.assert_array_equal(trained[RADIANCE.stop:], served[RADIANCE.stop:])
