"""torch vs ONNX Runtime parity of the exported crossreg U-Net on odd sizes, and the metadata contract."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from export.crossreg_unet import export_bytes  # noqa: E402
from export.onnx import initializers  # noqa: E402
from models.nets.crossreg_unet import make_unet  # noqa: E402
from service.layout import CROSSREG_INPUTS, CROSSREG_OUTPUTS, pad_planes  # noqa: E402
from service.runtime import ModelInfo, OnnxModel  # noqa: E402

ORT_RTOL = 1e-4  # float32 convolutions summed in a different order; precisions reach 1e4
ORT_ATOL = 1e-4


@pytest.fixture(scope="module")
def exported():
    net = make_unet(seed=7).eval()
    return net, export_bytes(net, extra={"note": "test"})


@pytest.mark.parametrize("size", [(13, 17), (1, 1), (5, 31), (24, 40)])
def test_torch_and_onnxruntime_agree_on_odd_sizes(exported, size):
    net, model_bytes = exported
    features = np.random.default_rng(size[0]).standard_normal((15, *size)).astype(np.float32)
    got = OnnxModel(model_bytes, threads=1).run_planes(features)
    with torch.no_grad():
        padded = torch.from_numpy(pad_planes(features, net.alignment)[None].copy())
        ref = net(padded).numpy()[0, :, : size[0], : size[1]]
    assert got.shape == (6, *size)
    np.testing.assert_allclose(got, ref, rtol=ORT_RTOL, atol=ORT_ATOL)


def test_metadata_carries_the_contract(exported):
    net, model_bytes = exported
    info = OnnxModel(model_bytes).info
    assert info.alignment == net.alignment == 4
    assert info.input_groups == CROSSREG_INPUTS and info.output_groups == CROSSREG_OUTPUTS
    assert [g.transform for g in info.input_groups][:3] == ["log1p"] * 3
    params = dict(net.named_parameters())
    assert info.weight_shapes == {k: tuple(v.shape) for k, v in params.items()}
    assert info.metadata["config"]["widths"] == [8, 16, 32] and info.metadata["note"] == "test"
    stored = initializers(model_bytes)
    for name, value in params.items():
        np.testing.assert_array_equal(stored[name], value.detach().numpy())
    assert ModelInfo.from_json(json.dumps(info.metadata)) == info  # the stored JSON is the whole contract


def test_shipped_warm_start_is_consistent_with_its_checkpoint_and_manifest():
    import json
    from pathlib import Path

    from models.nets.crossreg_unet import load_checkpoint

    folder = Path(__file__).resolve().parents[2] / "models" / "weights"
    net, ckpt = load_checkpoint(str(folder / "crossreg_unet.pt"))
    model_bytes = (folder / "crossreg_unet.onnx").read_bytes()
    stored = initializers(model_bytes)
    for name, value in net.named_parameters():
        np.testing.assert_array_equal(stored[name], value.detach().numpy(), err_msg=name)
    manifest = json.loads((folder / "crossreg_unet.json").read_text())
    assert manifest == ckpt["manifest"]
    assert {"seed", "steps", "data", "loss_last_200", "loss_curve_per_50_steps", "command"} <= set(manifest)
    assert OnnxModel(model_bytes).info.metadata["training"]["steps"] == manifest["steps"]
