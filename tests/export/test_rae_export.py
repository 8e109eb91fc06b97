"""torch vs ONNX Runtime parity of the exported recurrent autoencoder over several recurrent steps on odd
frame sizes (padded to the alignment as the pipeline pads), and the metadata contract it carries."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from export.rae import export_bytes, state_names  # noqa: E402
from models.nets.rae import RaeConfig, make_rae  # noqa: E402
from service.layout import RAE_INPUTS, RAE_OUTPUTS, groups_to_json, pad_planes  # noqa: E402
from service.runtime import METADATA_KEY, OnnxModel  # noqa: E402
from tests.tolerances import ORT_ATOL  # noqa: E402


@pytest.fixture(scope="module")
def exported():
    net = make_rae(RaeConfig(widths=(8, 12, 16)), seed=5).eval()
    return net, export_bytes(net, extra={"note": "test"})


@pytest.mark.parametrize("swappable", [True, False])
@pytest.mark.parametrize("size", [(13, 17), (1, 1), (37, 9)])
def test_torch_and_onnxruntime_agree_over_recurrent_steps(exported, size, swappable):
    net, model_bytes = exported
    model = OnnxModel(model_bytes, swappable=swappable)
    info = model.info
    rng = np.random.default_rng(size[0])
    h, w = size
    hidden_np, hidden_t = None, None
    for _step in range(4):
        planes = pad_planes(rng.standard_normal((8, h, w)).astype(np.float32), info.alignment)
        ph, pw = planes.shape[1:]
        if hidden_np is None:
            hidden_np = [np.zeros(spec.shape(ph, pw), np.float32) for spec in info.state]
            hidden_t = net.zero_hidden(1, ph, pw)
        state = {s.input: a for s, a in zip(info.state, hidden_np, strict=True)}
        out = model.run({info.input_name: planes[None], **state})
        with torch.no_grad():
            ref, *hidden_t = net(torch.from_numpy(planes[None]), *hidden_t)
        np.testing.assert_allclose(out[info.output_name], ref.numpy(), atol=ORT_ATOL, rtol=1e-4)
        hidden_np = [out[s.output] for s in info.state]
        for a, b in zip(hidden_np, hidden_t, strict=True):
            np.testing.assert_allclose(a, b.numpy(), atol=ORT_ATOL, rtol=1e-4)


def test_metadata_contract(exported):
    """One entry, under the key the runtime reads, with the contract the pipeline needs."""
    net, model_bytes = exported
    assert [p.key for p in onnx.load_from_string(model_bytes).metadata_props] == [METADATA_KEY]
    info = OnnxModel(model_bytes).info
    assert info.network == "rae" and info.alignment == net.alignment == 16
    assert info.input_name == "features" and info.output_name == "radiance"
    assert info.metadata["inputs"]["features"] == groups_to_json(RAE_INPUTS)
    assert info.metadata["outputs"]["radiance"] == groups_to_json(RAE_OUTPUTS)
    assert [(s.input, s.output) for s in info.state] == state_names(3)
    assert [(s.channels, s.scale) for s in info.state] == [(8, 2), (12, 4), (16, 8)]
    assert info.metadata["note"] == "test" and info.metadata["config"]["widths"] == [8, 12, 16]
    assert json.loads(json.dumps(info.metadata)) == info.metadata


def test_a_model_loaded_without_swapping_refuses_new_weights(exported):
    from service.runtime import WeightError

    _net, model_bytes = exported
    with pytest.raises(WeightError, match="without weight swapping"):
        OnnxModel(model_bytes, swappable=False).swap_weights({"head.bias": np.zeros(12, np.float32)})
