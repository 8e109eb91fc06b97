import numpy as np
import pytest

from service.stages.range_clamp import (
    _range_kernel,
    clamp_to_local_range,
    clamp_to_local_range_reference,
    local_range,
    local_range_reference,
)


def _brute(image, radius):
    h, w = image.shape[:2]
    lo, hi = np.empty_like(image), np.empty_like(image)
    for y in range(h):
        for x in range(w):
            win = image[max(0, y - radius) : y + radius + 1, max(0, x - radius) : x + radius + 1]
            lo[y, x], hi[y, x] = win.min(axis=(0, 1)), win.max(axis=(0, 1))
    return lo, hi


# windows of 1, 3, 7, 9, 13, 17 and 27 columns: spans only tripled (3, 9, 27), then doubled, then overlapped
@pytest.mark.parametrize(
    "shape,radius",
    [((1, 1), 3), ((3, 5), 1), ((17, 31), 8), ((9, 4), 0), ((12, 13), 6), ((11, 20), 4), ((30, 61), 13)],
)
def test_local_range_matches_brute_force(shape, radius):
    image = np.random.default_rng(0).normal(size=(*shape, 3)).astype(np.float32)
    lo, hi = local_range(image, radius)
    blo, bhi = _brute(image, radius)
    np.testing.assert_array_equal(lo, blo)
    np.testing.assert_array_equal(hi, bhi)


def test_clamp_removes_extrapolation_and_keeps_in_range_values():
    image = np.zeros((10, 10, 1), np.float32)
    image[5, 5] = 4.0
    output = np.full_like(image, 1.0)
    output[0, 0] = -0.5
    out = clamp_to_local_range(output, image, 2)
    assert out.min() == 0.0  # non-negative input: no negative output
    assert out[5, 5, 0] == 1.0 and out[0, 0, 0] == 0.0  # inside the window of the 4.0: unchanged
    assert out[9, 0, 0] == 0.0  # far from any non-zero input: the range is {0}


def test_constant_image_is_unchanged():
    image = np.full((6, 7, 3), 2.5, np.float32)
    np.testing.assert_array_equal(clamp_to_local_range(image, image, 4), image)


@pytest.mark.parametrize("shape,radius", [((1, 1), 3), ((3, 5), 1), ((17, 31), 8), ((9, 4), 0), ((40, 3), 5),
                                          ((90, 7), 2), ((33, 40), 6)])  # fmt: skip
def test_numba_kernel_matches_the_numpy_reference(shape, radius):
    rng = np.random.default_rng(1)
    image = rng.normal(size=(*shape, 3)).astype(np.float32)
    output = (2 * rng.normal(size=image.shape)).astype(np.float32)
    for fast, slow in zip(local_range(image, radius), local_range_reference(image, radius), strict=True):
        np.testing.assert_array_equal(fast, slow)
    np.testing.assert_array_equal(
        clamp_to_local_range(output, image, radius), clamp_to_local_range_reference(output, image, radius)
    )


def test_negative_radius_is_refused():
    image = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="radius must be >= 0, got -1"):
        clamp_to_local_range(image, image, -1)


@pytest.mark.parametrize("rows_per_task", [1, 4, 6, 7, 45, 90])
def test_every_band_split_matches_the_numpy_reference(rows_per_task):
    """Bands of 1 row, shorter and longer than a block of 2r+1 = 5 rows, of many blocks, and the whole
    frame: the split the thread count picks on other machines."""
    image = np.random.default_rng(2).normal(size=(90, 7, 3)).astype(np.float32)
    lo, hi = np.empty_like(image), np.empty_like(image)
    _range_kernel(image, image, 2, False, rows_per_task, lo, hi)
    for fast, slow in zip((lo, hi), local_range_reference(image, 2), strict=True):
        np.testing.assert_array_equal(fast, slow)
