"""clamp_outliers (service/stages/outliers.py): a firefly and a small cluster are clipped, a constant image,
a smooth gradient and an edge are not."""

import numpy as np

from service.stages.outliers import clamp_outliers


def test_firefly_and_small_cluster_are_clipped():
    image = np.ones((32, 32, 3), np.float32)
    image[5, 5] = 1000.0
    image[20:22, 20:22] = 500.0  # a 2x2 cluster: the 3x3 clamp alone cannot see it
    out = clamp_outliers(image)
    assert out[5, 5].max() < 10.0 and out[20:22, 20:22].max() < 10.0
    np.testing.assert_array_equal(out[:3, :3], image[:3, :3])


def test_constant_gradient_and_edge_are_unchanged():
    constant = np.full((17, 23, 3), 0.7, np.float32)
    np.testing.assert_array_equal(clamp_outliers(constant), constant)
    ramp = np.broadcast_to(np.linspace(0.1, 2.0, 23, dtype=np.float32)[None, :, None], (17, 23, 3)).copy()
    np.testing.assert_allclose(clamp_outliers(ramp), ramp, rtol=1e-6)
    edge = np.ones((17, 23, 3), np.float32)
    edge[:, 12:] = 50.0  # half the frame: signal, not an outlier
    np.testing.assert_array_equal(clamp_outliers(edge), edge)
