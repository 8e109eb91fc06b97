"""FLNR's guide network: the contract, and that an untrained network is FLR on the G-buffer (its guides are
the input's normal and relative depth exactly), so training starts from FLR."""

import pytest

torch = pytest.importorskip("torch")

from models.nets.flnr import BASE_GUIDES, FlnrConfig, make_flnr  # noqa: E402
from service.layout import FLNR_OUTPUTS, RAE_INPUTS, channel_slices, total_channels  # noqa: E402


def test_contract_and_alignment():
    net = make_flnr(seed=0)
    assert net.config.in_channels == total_channels(RAE_INPUTS) == 8
    assert net.config.guides == total_channels(FLNR_OUTPUTS) == 4
    assert net.alignment == 2 * 2**4
    slices = channel_slices(RAE_INPUTS)
    assert (BASE_GUIDES.start, BASE_GUIDES.stop) == (slices["normal"].start, slices["depth"].stop)
    with pytest.raises(ValueError, match="guides must be 4"):
        FlnrConfig(guides=3)
    with pytest.raises(ValueError, match="widths"):
        FlnrConfig(widths=())


def test_untrained_network_passes_the_gbuffer_guides_through_and_learns_from_there():
    net = make_flnr(FlnrConfig(widths=(4, 6)), seed=1)
    features = torch.randn(2, 8, 24, 40)
    out = net(features)
    assert torch.equal(out, features[:, BASE_GUIDES])
    out.square().sum().backward()  # the zeroed head still learns: its gradient is not zero
    assert net.head.weight.grad.abs().sum() > 0
