"""service/layout.py: channel planes stacked in a group order, edge padding of planes."""

import numpy as np
import pytest

from service.layout import CROSSREG_INPUTS, channel_slices, pad_planes, stack_planes


def _groups(height, width):
    rng = np.random.default_rng(0)
    return {g.name: rng.random((height, width, g.channels), np.float32) for g in CROSSREG_INPUTS}


def test_stack_planes_puts_every_group_in_its_slice():
    arrays = _groups(5, 7)
    planes = stack_planes(CROSSREG_INPUTS, arrays)
    assert planes.shape == (15, 5, 7) and planes.dtype == np.float32 and planes.flags.c_contiguous
    for name, where in channel_slices(CROSSREG_INPUTS).items():
        np.testing.assert_array_equal(planes[where], arrays[name].transpose(2, 0, 1))


def test_stack_planes_names_a_missing_or_misshapen_group():
    arrays = _groups(3, 4)
    del arrays["previous"]
    with pytest.raises(ValueError, match="network input 'previous' is missing"):
        stack_planes(CROSSREG_INPUTS, arrays)
    arrays["previous"] = np.zeros((3, 4, 2), np.float32)
    with pytest.raises(ValueError, match=r"'previous' has shape \(3, 4, 2\); expected \(H, W, 3\)"):
        stack_planes(CROSSREG_INPUTS, arrays)


@pytest.mark.parametrize("size", [(8, 12), (5, 7), (1, 1)])
def test_pad_planes_replicates_the_last_row_and_column(size):
    planes = np.random.default_rng(1).random((3, *size), np.float32)
    padded = pad_planes(planes, 4)
    height, width = size
    assert padded.shape == (3, -(-height // 4) * 4, -(-width // 4) * 4)
    np.testing.assert_array_equal(padded[:, :height, :width], planes)
    assert (padded[:, height:, :width] == planes[:, -1:, :]).all()  # rows below: copies of the last row
    assert (padded[:, :, width:] == padded[:, :, width - 1 : width]).all()  # columns right: of the last column
    if size == (8, 12):
        assert np.shares_memory(padded, planes)  # aligned already: no copy
