"""The recurrent autoencoder (Chaitanya 2017 sec. 4): contract, shapes, the recurrence, initialisation."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.nets import count_parameters, state_for  # noqa: E402
from models.nets.rae import (  # noqa: E402
    LEAKY_SLOPE,
    SPACE_TO_DEPTH,
    RaeConfig,
    load_network,
    make_rae,
)
from service.layout import RAE_INPUTS, RAE_OUTPUTS, total_channels  # noqa: E402


def test_contract_alignment_and_size():
    net = make_rae(seed=0)
    assert net.config.in_channels == total_channels(RAE_INPUTS) == 8
    assert net.config.out_channels == total_channels(RAE_OUTPUTS) == 3
    assert net.alignment == SPACE_TO_DEPTH * 2 ** len(net.config.widths) == 32
    assert count_parameters(net) * 4 < 5e6  # float32 weights within the 5 MB


def test_shapes_of_output_and_hidden_state():
    net = make_rae(RaeConfig(widths=(4, 6, 8)), seed=0).eval()
    assert net.config.scales == (2, 4, 8) and net.alignment == 16
    hidden = net.zero_hidden(2, 32, 48)
    assert [tuple(h.shape) for h in hidden] == [(2, 4, 16, 24), (2, 6, 8, 12), (2, 8, 4, 6)]
    out, *new = net(torch.randn(2, 8, 32, 48), *hidden)
    assert out.shape == (2, 3, 32, 48)
    assert [h.shape for h in new] == [h.shape for h in hidden]


def test_hidden_state_carries_the_previous_frame():
    """Same frame, different history: the output differs; same history: identical output."""
    net = make_rae(RaeConfig(widths=(4, 6)), seed=1).eval()
    x, other = torch.randn(1, 8, 16, 16), torch.randn(1, 8, 16, 16)
    with torch.no_grad():
        _, *after_x = net(x, *net.zero_hidden(1, 16, 16))
        _, *after_other = net(other, *net.zero_hidden(1, 16, 16))
        a = net(x, *after_x)[0]
        b = net(x, *after_other)[0]
        c = net(x, *after_x)[0]
    assert not torch.allclose(a, b)
    assert torch.equal(a, c)


def test_each_output_pixel_sees_its_own_full_resolution_input():
    """Space-to-depth must not lose a sub-pixel: changing one input pixel changes that output pixel."""
    net = make_rae(RaeConfig(widths=(4, 6)), seed=2).eval()
    x = torch.randn(1, 8, 16, 16)
    with torch.no_grad():
        base = net(x, *net.zero_hidden(1, 16, 16))[0]
        for y, xx in [(5, 5), (5, 6), (6, 5), (6, 6)]:
            moved = x.clone()
            moved[0, 0, y, xx] += 1.0
            out = net(moved, *net.zero_hidden(1, 16, 16))[0]
            assert (out - base)[0, :, y, xx].abs().max() > 0


def test_he_initialisation_for_leaky_relu():
    net = make_rae(seed=3)
    conv = net.encoder[1].mix  # 2 * 48 channels in, 3x3
    fan_in = conv.weight[0].numel()
    expected = np.sqrt(2.0 / (1 + LEAKY_SLOPE**2) / fan_in)
    assert conv.weight.std().item() == pytest.approx(expected, rel=0.05)
    assert torch.count_nonzero(conv.bias) == 0


def test_checkpoint_round_trip():
    net = make_rae(RaeConfig(widths=(4, 6)), seed=4)
    again = load_network(state_for(net))
    assert again.config == net.config
    x = torch.randn(1, 8, 8, 8)
    with torch.no_grad():
        assert torch.equal(net.eval()(x, *net.zero_hidden(1, 8, 8))[0], again(x, *again.zero_hidden(1, 8, 8))[0])
