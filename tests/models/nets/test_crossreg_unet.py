"""The crossreg U-Net (Choi 2024 sec. 4.4): size, contract, head ranges, checkpoint round trip."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.nets import count_parameters  # noqa: E402
from models.nets.crossreg_unet import (  # noqa: E402
    CrossRegUNet,
    UNetConfig,
    load_checkpoint,
    make_unet,
    save_checkpoint,
)
from service.layout import CROSSREG_INPUTS, CROSSREG_OUTPUTS, total_channels  # noqa: E402


def test_about_30k_parameters_and_the_layout_contract():
    net = make_unet(seed=0)
    assert 28_000 <= count_parameters(net) <= 32_000  # "about 30K" (sec. 4.4); ours: 30,086
    assert net.config.in_channels == total_channels(CROSSREG_INPUTS) == 15
    assert net.config.out_channels == total_channels(CROSSREG_OUTPUTS) == 6
    assert net.alignment == 4


def test_head_keeps_precisions_positive_and_alpha_in_unit_interval():
    net = make_unet(seed=1)
    with torch.no_grad():
        out = net(torch.randn(2, 15, 12, 20) * 5)
    assert out.shape == (2, 6, 12, 20)
    precisions, alpha = out[:, :5], out[:, 5]
    assert (precisions > 0).all() and (precisions <= 1 / net.config.eps + 1).all()
    assert ((alpha > 0) & (alpha < 1)).all()


def test_seeded_init_is_reproducible_and_checkpoint_stores_constructor_args(tmp_path):
    a, b = make_unet(seed=3), make_unet(seed=3)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)
    net = CrossRegUNet(UNetConfig(widths=(4, 8, 16)))
    save_checkpoint(str(tmp_path / "c.pt"), net, manifest={"steps": 1})
    loaded, ckpt = load_checkpoint(str(tmp_path / "c.pt"))
    assert loaded.config == net.config and ckpt["manifest"] == {"steps": 1}
    x = torch.from_numpy(np.random.default_rng(0).random((1, 15, 8, 8), np.float32))
    with torch.no_grad():
        assert torch.equal(loaded(x), net(x))
