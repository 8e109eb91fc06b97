import numpy as np
import pytest

from service.metrics import rel_l2, rel_l2_map


def test_rel_l2_by_hand():
    ref = np.full((1, 2, 3), 1.0, np.float32)
    img = ref.copy()
    img[0, 0] = 2.0
    # pixel 0: (1)^2 / (1 + 0.01) per channel; pixel 1: 0
    assert rel_l2(img, ref) == pytest.approx(0.5 / 1.01)
    np.testing.assert_allclose(rel_l2_map(img, ref), [[1 / 1.01, 0.0]])


def test_trim_drops_the_worst_pixels():
    ref = np.zeros((10, 100, 3), np.float32)
    img = ref.copy()
    img[0, 0] = 100.0  # one aliased pixel of 1000
    assert rel_l2(img, ref) > 1.0
    assert rel_l2(img, ref, trim=0.001) == 0.0
    with pytest.raises(ValueError):
        rel_l2(img, ref, trim=1.0)
