"""torch vs ONNX Runtime parity of FLNR's exported guide network on odd frame sizes (padded to the alignment
as the pipeline pads), and the metadata contract the pipeline reads."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from export.flnr import export_bytes  # noqa: E402
from models.nets.flnr import FlnrConfig, make_flnr  # noqa: E402
from models.train.flnr import FLR  # noqa: E402
from service.layout import FLNR_OUTPUTS, RAE_INPUTS, groups_to_json, pad_planes  # noqa: E402
from service.pipelines.flnr import regression_params  # noqa: E402
from service.runtime import OnnxModel  # noqa: E402
from tests.tolerances import ORT_ATOL  # noqa: E402


@pytest.fixture(scope="module")
def exported():
    net = make_flnr(FlnrConfig(widths=(6, 8, 10)), seed=3).eval()
    return net, export_bytes(net, extra={"note": "test"})


@pytest.mark.parametrize("size", [(13, 17), (1, 1), (37, 70)])
def test_torch_and_onnxruntime_agree(exported, size):
    net, model_bytes = exported
    model = OnnxModel(model_bytes, swappable=False)
    planes = pad_planes(np.random.default_rng(size[0]).standard_normal((8, *size)).astype(np.float32),
                        model.info.alignment)
    out = model.run({model.info.input_name: planes[None]})[model.info.output_name]
    with torch.no_grad():
        ref = net(torch.from_numpy(planes[None])).numpy()
    assert out.shape == ref.shape == (1, FLNR_OUTPUTS[0].channels, *planes.shape[1:])
    np.testing.assert_allclose(out, ref, atol=ORT_ATOL, rtol=1e-4)


def test_metadata_contract(exported):
    net, model_bytes = exported
    info = OnnxModel(model_bytes).info
    assert info.network == "flnr" and info.alignment == net.alignment == 16
    assert info.input_name == "features" and info.output_name == "guides"
    assert info.metadata["inputs"]["features"] == groups_to_json(RAE_INPUTS)
    assert info.metadata["outputs"]["guides"] == groups_to_json(FLNR_OUTPUTS)
    assert info.metadata["note"] == "test" and not info.state
    params = regression_params(OnnxModel(model_bytes))
    assert (params.scale, params.sigma) == (FLR.scale, FLR.sigma)  # the pipeline regresses as training did
