import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from service.stages.reprojection import ReprojectionParams, erode, reproject, reproject_numpy


def _motion(h, w, x, y):
    return np.broadcast_to(np.float32([x, y]), (h, w, 2)).copy()


def test_integer_shift_is_undone_exactly():
    rng = np.random.default_rng(0)
    prev = rng.normal(size=(9, 13, 4)).astype(np.float32) * 1e3
    # the scene moved 2 right, 1 down: what is at (x, y) now was at (x - 2, y - 1)
    warped, valid = reproject(prev, _motion(9, 13, -2, -1))
    assert valid[1:, 2:].all() and not valid[0].any() and not valid[:, :2].any()
    np.testing.assert_array_equal(warped[1:, 2:], prev[:-1, :-2])
    assert np.all(warped[~valid] == 0)


def test_bilinear_half_pixel_and_off_screen():
    prev = np.arange(12, dtype=np.float32).reshape(3, 4, 1)
    warped, valid = reproject(prev, _motion(3, 4, 0.5, 0))
    np.testing.assert_allclose(warped[:, :3, 0], 0.5 * (prev[:, :3, 0] + prev[:, 1:, 0]))
    # the last column samples x = 3.5, outside the frame's pixel area [-0.5, 3.5)
    assert valid[:, :3].all() and not valid[:, 3].any()
    warped, valid = reproject(prev, _motion(3, 4, 1e30, 0))
    assert not valid.any() and np.isfinite(warped).all()


def test_inconsistent_taps_are_dropped_and_the_rest_renormalised():
    prev = np.float32([[[1.0], [5.0]]])  # 1x2
    depth = np.float32([[[2.0], [2.0]]])
    prev_depth = np.float32([[[2.0], [9.0]]])  # right pixel was another surface
    warped, valid = reproject(prev, _motion(1, 2, 0.5, 0), depth=depth, prev_depth=prev_depth)
    assert valid[0, 0] and warped[0, 0, 0] == 1.0  # only the consistent left tap counts
    normal = np.float32([[[0, 0, 1], [0, 0, 1]]])
    prev_normal = np.float32([[[0, 0, 1], [1, 0, 0]]])
    warped, valid = reproject(prev, _motion(1, 2, 0, 0), normal=normal, prev_normal=prev_normal)
    assert valid[0, 0] and not valid[0, 1]


def test_depth_and_normal_mismatch_invalidate():
    h, w = 6, 7
    prev = np.ones((h, w, 3), np.float32)
    depth = np.full((h, w, 1), 4.0, np.float32)
    prev_depth = depth.copy()
    prev_depth[2, 3] = 4.5  # 12.5% relative change > 10%
    _, valid = reproject(prev, _motion(h, w, 0, 0), depth=depth, prev_depth=prev_depth)
    assert not valid[2, 3] and valid.sum() == h * w - 1
    normal = np.tile(np.float32([0, 1, 0]), (h, w, 1))
    prev_normal = normal.copy()
    prev_normal[4, 4] = 0  # nothing was hit there
    _, valid = reproject(prev, _motion(h, w, 0, 0), normal=normal, prev_normal=prev_normal)
    assert not valid[4, 4] and valid.sum() == h * w - 1
    _, valid = reproject(prev, _motion(h, w, 0, 0), normal=np.zeros_like(normal), prev_normal=np.zeros_like(normal))
    assert valid.all()  # background stays background


def test_erosion():
    valid = np.ones((5, 6), bool)
    valid[2, 3] = False
    eroded = erode(valid)
    assert eroded.sum() == 30 - 9 and not eroded[1:4, 2:5].any()
    prev = np.ones((5, 6, 1), np.float32)
    motion = _motion(5, 6, 0, 0)
    motion[2, 3] = 100.0
    warped, valid = reproject(prev, motion, params=ReprojectionParams(erode=True))
    assert valid.sum() == 21 and np.all(warped[~valid] == 0)


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (17, 31)])
def test_odd_sizes_float16_and_negative_values(shape):
    rng = np.random.default_rng(1)
    h, w = shape
    prev = rng.normal(size=(h, w, 3)).astype(np.float16).astype(np.float32)
    motion = rng.normal(0, 2, (h, w, 2)).astype(np.float16).astype(np.float32)
    depth = (1 + rng.random((h, w, 1))).astype(np.float32)
    warped, valid = reproject(prev, motion, depth=depth, prev_depth=depth)
    assert warped.shape == prev.shape and warped.dtype == np.float32 and valid.shape == (h, w)
    assert np.isfinite(warped).all()
    inside = warped[valid]  # a convex combination of previous values; zero where invalid
    assert np.all(inside >= prev.min() - 1e-6) and np.all(inside <= prev.max() + 1e-6)
    assert np.all(warped[~valid] == 0)


def test_constant_buffer_is_unchanged_where_valid():
    prev = np.full((8, 9, 2), -3.25, np.float32)
    warped, valid = reproject(prev, np.random.default_rng(2).normal(0, 1.5, (8, 9, 2)).astype(np.float32))
    assert valid.any()
    np.testing.assert_allclose(warped[valid], -3.25, atol=1e-6)


def test_depth_without_prev_depth_is_refused():
    with pytest.raises(ValueError, match="both or neither"):
        reproject(np.ones((2, 2, 1), np.float32), _motion(2, 2, 0, 0), depth=np.ones((2, 2, 1), np.float32))
    with pytest.raises(ValueError, match="depth_tolerance"):
        ReprojectionParams(depth_tolerance=0)


@pytest.mark.parametrize("shape", [(1, 1), (5, 3), (23, 37)])
@pytest.mark.parametrize("guided, erode_mask", [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("spline", [False, True])
def test_compiled_reproject_matches_numpy_reference(shape, guided, erode_mask, spline):
    """Also with the spline; its cases keep most 4x4 blocks on one surface (depth and normal) so that it is taken
    somewhere, and set scattered taps of other surfaces."""
    rng = np.random.default_rng(5)
    h, w = shape
    prev = rng.normal(size=(h, w, 6)).astype(np.float32)
    motion = rng.normal(0, 2, (h, w, 2)).astype(np.float32)
    motion[0, 0] = np.nan  # invalid, as off-screen motion
    motion.flat[1::7] = np.round(motion.flat[1::7])  # integer motion: taps of weight zero
    if spline:  # sub-pixel motion, so that most 4x4 blocks are inside and the spline is taken
        motion = np.where(np.isnan(motion), motion, motion * np.float32(0.25))
    kwargs = {"params": ReprojectionParams(erode=erode_mask, catmull_rom=spline)}
    if guided:
        depth = (2 + rng.random((h, w, 1)) * (0.02 if spline else 1.0)).astype(np.float32)  # spline: one surface
        normal = np.tile(np.float32([0, 0, 1]), (h, w, 1))
        prev_normal = normal.copy()
        step = (7, 9) if spline else (3, 4)  # sparser with the spline, which needs a 4x4 block consistent
        prev_normal[:: step[0]] = np.float32([0, 0.6, 0.8])  # cos 0.8 < 0.9: inconsistent
        prev_normal[1 :: step[1]] = 0  # nothing hit
        kwargs.update(
            depth=depth,
            prev_depth=depth * _depth_change(rng, (h, w, 1), spline),
            normal=normal,
            prev_normal=prev_normal,
        )
    warped, valid = reproject(prev, motion, **kwargs)
    with np.errstate(invalid="ignore"):  # the reference casts the NaN position before discarding it
        expected, expected_valid = reproject_numpy(prev, motion, **kwargs)
    np.testing.assert_array_equal(valid, expected_valid)
    np.testing.assert_allclose(warped, expected, rtol=1e-6, atol=1e-6 if spline else 1e-7)
    if spline and min(shape) > 4:  # the spline was taken somewhere: it differs from the bilinear sample there
        bilinear, _ = reproject(prev, motion, **{**kwargs, "params": ReprojectionParams(erode=erode_mask)})
        assert (np.abs(warped - bilinear) > 1e-3).any()


SPLINE = ReprojectionParams(catmull_rom=True)


def test_catmull_rom_keeps_integer_shifts_and_reproduces_a_quadratic():
    rng = np.random.default_rng(0)
    prev = rng.normal(size=(9, 13, 2)).astype(np.float32)
    warped, valid = reproject(prev, _motion(9, 13, -2, -1), params=SPLINE)
    np.testing.assert_array_equal(warped[1:, 2:], prev[:-1, :-2])
    x = np.arange(12, dtype=np.float32)
    ramp = np.broadcast_to(((x + 3.0) ** 2)[None, :, None], (8, 12, 1)).copy()  # increasing: no extremum inside
    warped, valid = reproject(ramp, _motion(8, 12, 0.3, 0), params=SPLINE)
    want = (x + 3.3) ** 2
    np.testing.assert_allclose(warped[3, 1:10, 0], want[1:10], rtol=1e-6)  # its 4x4 taps inside: exact
    bilinear, _ = reproject(ramp, _motion(8, 12, 0.3, 0))
    np.testing.assert_allclose(bilinear[3, 1:10, 0] - want[1:10], 0.3 * 0.7, rtol=1e-4)  # bilinear: t (1 - t) f''/2
    np.testing.assert_array_equal(warped[:, [0, 10], :], bilinear[:, [0, 10], :])  # a tap outside: bilinear
    np.testing.assert_array_equal(warped[[0, 7]], bilinear[[0, 7]])


def test_catmull_rom_does_not_overshoot_an_edge():
    step = np.zeros((6, 10, 1), np.float32)
    step[:, 5:] = 100.0
    warped, valid = reproject(step, _motion(6, 10, 0.5, 0), params=SPLINE)
    assert valid[:, :9].all() and warped.min() == 0.0 and warped.max() == 100.0
    # row 2 takes the spline (its 4x4 blocks are inside for columns 1-7): at column 3 it gives -6.25 and at
    # column 5 106.25 (weights -1/16, 9/16, 9/16, -1/16), clamped to the 2x2 taps' 0 and 100
    np.testing.assert_array_equal(warped[2, 1:8, 0], [0.0, 0.0, 0.0, 50.0, 100.0, 100.0, 100.0])


def test_catmull_rom_needs_every_tap_consistent():
    rng = np.random.default_rng(1)
    prev = rng.normal(size=(8, 10, 3)).astype(np.float32)
    depth = np.full((8, 10, 1), 3.0, np.float32)
    prev_depth = depth.copy()
    prev_depth[4, 7] = 9.0  # another surface, an outer tap of the samples right of column 4 in rows 3-6
    motion = _motion(8, 10, 0.4, 0.3)
    warped, _ = reproject(prev, motion, depth=depth, prev_depth=prev_depth, params=SPLINE)
    bilinear, _ = reproject(prev, motion, depth=depth, prev_depth=prev_depth)
    np.testing.assert_array_equal(warped[3, 5], bilinear[3, 5])  # its 4x4 block holds (4, 7)
    assert not np.allclose(warped[3, 2], bilinear[3, 2])  # its block does not: the spline


def test_catmull_rom_blurs_a_history_less_than_bilinear():
    """A texture (rows of a sinusoid of period 8 pixels) warped half a pixel right and back, 8 times each:
    bilinear samples blur it frame after frame."""
    phase = np.random.default_rng(2).random((16, 1)) * 2 * np.pi
    texture = (0.5 + 0.5 * np.sin(2 * np.pi * np.arange(32) / 8 + phase))[..., None].astype(np.float32)
    results = {}
    for name, params in (("bilinear", None), ("spline", SPLINE)):
        history = texture
        for k in range(16):
            history, _ = reproject(history, _motion(16, 32, 0.5 if k % 2 == 0 else -0.5, 0), params=params)
        results[name] = np.abs(history[:, 6:26] - texture[:, 6:26]).mean()
    assert results["spline"] < 0.5 * results["bilinear"]  # measured: 0.098 against 0.231


def _depth_change(rng, shape, spline):
    """prev_depth / depth: within +-15% (half the pixels beyond the 10% tolerance), or with `spline` within +-3%
    but for one pixel in 42, 50% deeper."""
    if not spline:
        return rng.uniform(0.85, 1.15, shape).astype(np.float32)
    change = rng.uniform(0.97, 1.03, shape)
    change[2::6, 3::7] *= 1.5
    return change.astype(np.float32)


def test_channel_planar_buffer_gives_a_channel_planar_result_with_the_same_values():
    """crossreg keeps its history as planes (C, H, W) and reprojects the (H, W, C) view of them."""
    rng = np.random.default_rng(6)
    planes = rng.normal(size=(9, 11, 14)).astype(np.float32)
    motion = rng.normal(0, 1.5, (11, 14, 2)).astype(np.float32)
    params = ReprojectionParams(erode=True)
    warped, valid = reproject(planes.transpose(1, 2, 0), motion, params=params)
    expected, expected_valid = reproject(np.ascontiguousarray(planes.transpose(1, 2, 0)), motion, params=params)
    assert warped.transpose(2, 0, 1).flags.c_contiguous and expected.flags.c_contiguous
    np.testing.assert_array_equal(valid, expected_valid)
    np.testing.assert_array_equal(warped, expected)
    assert 0 < valid.mean() < 1 and not warped[~valid].any()


@pytest.mark.slow
def test_spline_of_a_strided_buffer_after_a_crossreg_run_in_a_fresh_cache(tmp_path):
    """A fresh kernel cache, crossreg over three frames (which compiles the kernel for planar views, (H, W, C)
    of (C, H, W), and for contiguous buffers), then the spline of a planar view against the numpy twin. With
    the spline's helpers inlined (numba `inline="always"`) the planar view's result was wrong by up to 3.1 on
    values of unit spread in this order of compilation (numba 0.68.1); as plain calls it is exact."""
    script = textwrap.dedent("""
        import numpy as np
        from bench.synthetic import synthetic_sequence
        from service import pipelines
        from service.frame import Frame
        from service.stages.reprojection import ReprojectionParams, reproject, reproject_numpy
        frames = [Frame.from_buffers(x) for x in synthetic_sequence(24, 28, 3, spp=4, seed=7)]
        pipeline = pipelines.get("crossreg")
        state = pipeline.start(24, 28)
        for frame in frames:
            _, state = pipeline.step(frame, state)
        rng = np.random.default_rng(5)
        planes = rng.normal(size=(9, 40, 50)).astype(np.float32)
        motion = (rng.normal(0, 1, (40, 50, 2)) * 0.3).astype(np.float32)
        params = ReprojectionParams(erode=True, catmull_rom=True)
        got, _ = reproject(planes.transpose(1, 2, 0), motion, params=params)
        want, _ = reproject_numpy(np.ascontiguousarray(planes.transpose(1, 2, 0)), motion, params=params)
        print(float(np.abs(got - want).max()))
    """)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=False)
    assert run.returncode == 0, run.stderr
    assert float(run.stdout.split()[-1]) < 1e-5
