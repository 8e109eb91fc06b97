import numpy as np

from service.stages.sample_statistics import SampleStatistics, box_cox, statistics_from_samples


def test_box_cox_half_matches_eq15():
    x = np.array([0.0, 1.0, 4.0, 9.0], np.float32)
    np.testing.assert_allclose(box_cox(x), (np.sqrt(x) - 1) / 0.5)
    assert np.isfinite(box_cox(np.array([-4.0], np.float32))).all()


def test_online_moments_equal_two_pass_moments():
    rng = np.random.default_rng(0)
    samples = rng.gamma(0.5, 2.0, (11, 3, 4, 3)).astype(np.float32)
    layers = statistics_from_samples(samples)
    x = box_cox(samples).astype(np.float64)
    d = x - x.mean(axis=0)
    np.testing.assert_allclose(layers["bcMean"], x.mean(axis=0), atol=1e-5)
    np.testing.assert_allclose(layers["bcM2"], (d**2).mean(axis=0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(layers["bcM3"], (d**3).mean(axis=0), rtol=1e-3, atol=1e-4)
    assert np.all(layers["sampleCount"] == 11)


def test_constant_samples_have_zero_central_moments():
    stats = SampleStatistics.empty(2, 2)
    for _ in range(5):
        stats.add(np.full((2, 2, 3), 4.0, np.float32))
    layers = stats.layers()
    np.testing.assert_allclose(layers["bcMean"], 2.0)
    assert np.all(layers["bcM2"] == 0) and np.all(layers["bcM3"] == 0)
