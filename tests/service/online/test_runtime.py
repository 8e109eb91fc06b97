"""service/runtime.py: metadata-driven padding, weight hot-swap, refusal of bad or non-finite weights."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from export.crossreg_unet import export_bytes  # noqa: E402
from models.nets.crossreg_unet import make_unet  # noqa: E402
from service.layout import pad_planes  # noqa: E402
from service.runtime import (  # noqa: E402
    NonFiniteWeightsError,
    OnnxModel,
    WeightError,
    default_init,
    session_options,
)


@pytest.fixture(scope="module")
def model_bytes():
    return export_bytes(make_unet(seed=0))


def _torch_out(net, planes):
    """The torch network on planes (C, H, W), padded to its alignment and cropped back."""
    with torch.no_grad():
        out = net(torch.from_numpy(pad_planes(planes, net.alignment)[None].copy()))
    return out.numpy()[0, :, : planes.shape[1], : planes.shape[2]]


def test_swap_changes_the_output_to_the_new_weights(model_bytes):
    model = OnnxModel(model_bytes, threads=1)
    features = np.random.default_rng(1).standard_normal((15, 13, 17)).astype(np.float32)
    before = model.run_planes(features)
    other = make_unet(seed=99)
    new = {k: v.detach().numpy() for k, v in other.named_parameters()}
    assert model.swap_weights(new) == 1 and model.version == 1
    after = model.run_planes(features)
    assert np.abs(after - before).max() > 1e-3
    np.testing.assert_allclose(after, _torch_out(other, features), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("size", [(13, 17), (8, 12)])
def test_run_planes_matches_torch_and_crops_the_padding(model_bytes, size):
    model = OnnxModel(model_bytes, threads=1)
    features = np.random.default_rng(3).standard_normal((15, *size)).astype(np.float32)
    planes = model.run_planes(features)
    assert planes.shape == (6, *size) and planes.flags.c_contiguous
    np.testing.assert_allclose(planes, _torch_out(make_unet(seed=0), features), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match=r"network input has shape \(14, 8, 12\); expected \(15, H, W\)"):
        model.run_planes(np.zeros((14, 8, 12), np.float32))


def test_partial_swap_keeps_earlier_overrides(model_bytes):
    model = OnnxModel(model_bytes, threads=1)
    zero_head = {"head.weight": np.zeros((6, 8, 1, 1), np.float32), "head.bias": np.full(6, 2.0, np.float32)}
    model.swap_weights(zero_head)
    model.swap_weights({"enc1.0.0.bias": np.zeros(8, np.float32)})
    out = model.run_planes(np.ones((15, 4, 4), np.float32))
    np.testing.assert_allclose(out[:5], 1 / (4 + 1e-4), rtol=1e-5)  # head still zero, bias 2
    np.testing.assert_allclose(out[5], 1 / (1 + np.exp(-2.0)), rtol=1e-5)


@pytest.mark.parametrize(
    "bad, error, text",
    [
        ({"head.bias": np.array([np.nan, 0, 0, 0, 0, 0], np.float32)}, NonFiniteWeightsError, "non-finite"),
        ({"head.bias": np.full(6, np.inf, np.float32)}, NonFiniteWeightsError, "6 non-finite"),
        ({"head.bias": np.zeros(5, np.float32)}, WeightError, r"shape \(5,\); the graph needs \(6,\)"),
        ({"nope.weight": np.zeros(3, np.float32)}, WeightError, "'nope.weight' is not a weight"),
        ({"head.bias": np.zeros(6, np.int32)}, WeightError, "dtype int32"),
        ({}, WeightError, "no weights"),
    ],
)
def test_bad_weights_are_refused_and_the_session_keeps_running(model_bytes, bad, error, text):
    model = OnnxModel(model_bytes, threads=1)
    features = np.random.default_rng(2).standard_normal((15, 5, 7)).astype(np.float32)
    before = model.run_planes(features)
    with pytest.raises(error, match=text):
        model.swap_weights(bad)
    assert model.version == 0
    np.testing.assert_array_equal(model.run_planes(features), before)


def test_default_init_has_pytorch_bounds(model_bytes):
    model = OnnxModel(model_bytes)
    weights = default_init(model.info.weight_shapes, seed=0)
    assert set(weights) == set(model.info.weight_shapes)
    bound = 1 / np.sqrt(15 * 9)
    assert np.abs(weights["enc1.0.0.weight"]).max() <= bound and np.abs(weights["enc1.0.0.bias"]).max() <= bound
    model.swap_weights(weights)
    assert np.isfinite(model.run_planes(np.zeros((15, 3, 3), np.float32))).all()


def test_thread_setting_from_argument_and_environment(monkeypatch):
    assert session_options(3).intra_op_num_threads == 3
    monkeypatch.setenv("MCDENOISE_ORT_THREADS", "2")
    assert session_options().intra_op_num_threads == 2
    monkeypatch.setenv("MCDENOISE_ORT_THREADS", "many")
    with pytest.raises(ValueError, match="MCDENOISE_ORT_THREADS must be an integer"):
        session_options()


def test_model_without_metadata_is_refused():
    import onnx
    from onnx import helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "g",
        [helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    with pytest.raises(ValueError, match="no 'mcdenoise' metadata"):
        OnnxModel(model.SerializeToString())
