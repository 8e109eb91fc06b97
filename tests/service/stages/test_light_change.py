"""Where both halves say the light changed against a history (service/stages/light_change.py)."""

import warnings

import numpy as np

from service.stages.light_change import light_changed, robust_mean

CHANGE = 1.5


def test_light_changed_only_where_both_halves_agree_on_a_change_and_at_any_scale():
    rng = np.random.default_rng(5)
    history = rng.uniform(0.5, 1.5, (6, 16, 16)).astype(np.float32)
    assert not light_changed(history, history, CHANGE, 8.0).any()
    halves = history.copy()
    halves[0:3, 4:9, 4:9] *= 1.2 * CHANGE  # half A alone brighter: a firefly's pattern, not a change
    assert not light_changed(halves, history, CHANGE, 8.0).any()
    halves[3:6, 4:9, 4:9] *= 1.2 * CHANGE  # both brighter
    changed = light_changed(halves, history, CHANGE, 8.0)
    assert changed[5:8, 5:8].all() and not changed[12:, 12:].any()
    for scale in (1e-6, 1e6):
        np.testing.assert_array_equal(light_changed(halves * scale, history * scale, CHANGE, 8.0), changed)


def test_a_pixel_that_went_dark_alone_changes_only_with_the_pixel_test():
    """One pixel of both halves 10x darker than the history, its neighbours as before (a thin shadow): its 3x3
    means move by 10%, less than CHANGE, so only the pixel test (at 8x) sees it."""
    history = np.ones((6, 9, 9), np.float32)
    halves = history.copy()
    halves[:, 4, 4] = 0.1
    assert not light_changed(halves, history, CHANGE, np.inf).any()
    changed = light_changed(halves, history, CHANGE, 8.0)
    assert changed[4, 4] and changed.sum() == 1


def test_radiance_near_float32s_largest_warns_nothing():
    """Sums of 3e38 overflow to inf: the test still answers, without a warning, and sees no change where both the
    frame and the history are that large; a history of 3e38 under a frame of 1 is a change (darker)."""
    history = np.ones((6, 8, 8), np.float32)
    halves = history.copy()
    halves[:, :, 4:] = 3e38
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not light_changed(halves, halves, CHANGE, 8.0).any()
        assert light_changed(history, history * np.float32(3e38), CHANGE, 8.0).all()
        assert not light_changed(halves, history, CHANGE, 8.0)[:, :3].any()  # a frame mean of inf: eps 1e30


def test_negative_radiance_counts_as_zero_without_sign_flips_or_division_by_zero():
    """Halves and history a little below 0 (a light's edge less its emission) are as dark as 0: no change and no
    warning, also where a sum plus eps would have been exactly 0; a lit history above them is a change."""
    history = np.full((6, 8, 8), -1e-3, np.float32)
    halves = np.full((6, 8, 8), -2e-3, np.float32)
    halves[:, 0, 0] = 1.0  # a frame mean above 0: eps = 1e-3 of it
    eps = 1e-3 * float(np.maximum(np.stack([halves[0:3].sum(0), halves[3:6].sum(0)], -1), 0).mean())
    history[:, 4, 4] = -eps / 3  # its sum plus eps: 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not light_changed(halves, history, CHANGE, 8.0)[2:, 2:].any()
        assert light_changed(halves, np.ones_like(history), CHANGE, 8.0)[2:, 2:].all()


def test_one_huge_firefly_does_not_blind_the_test():
    """A shadow moved in (both halves 10x darker over a 5x5 patch) in a frame that also holds one pixel of 1e10 in
    half A: the eps from the frame's plain mean (about 1e6 here) would make every ratio about 1."""
    rng = np.random.default_rng(7)
    history = rng.uniform(0.5, 1.5, (6, 64, 64)).astype(np.float32)
    halves = history.copy()
    halves[:, 10:15, 10:15] *= 0.1
    expected = light_changed(halves, history, CHANGE, 8.0)
    assert expected[11:14, 11:14].all()
    halves[0:3, 40, 40] = 1e10
    history_too = history.copy()
    history_too[0:3, 40, 40] = 1e10  # the firefly stays where it was: no change there either
    np.testing.assert_array_equal(light_changed(halves, history_too, CHANGE, 8.0), expected)


def test_the_robust_mean_caps_only_the_top_of_the_frame():
    rng = np.random.default_rng(8)
    values = rng.uniform(0.0, 2.0, (720, 1280, 2)).astype(np.float32)
    np.testing.assert_allclose(robust_mean(values), values.mean(dtype=np.float64), rtol=1e-2)  # a sample, capped
    spiked = values.copy()
    spiked[::25, ::25, 0] = 1e10  # 0.08% of the values, all in half A: 0.16% of a sample that held half A alone
    assert robust_mean(spiked) < 1.01 * robust_mean(values)
    assert robust_mean(np.zeros((3, 3, 2), np.float32)) == 0.0
    assert robust_mean(np.full((1, 1, 2), 5.0, np.float32)) == 5.0
