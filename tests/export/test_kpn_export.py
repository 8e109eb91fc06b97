"""torch vs ONNX Runtime parity of the exported kernel-predicting network over several recurrent steps on odd
frame sizes (padded to the alignment as the pipeline pads; each side feeds back its own filtered output),
and the metadata contract it carries."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from export.kpn import COARSE_OUTPUTS, export_bytes  # noqa: E402
from models.nets.kpn import KpnConfig, make_kpn  # noqa: E402
from models.train.kernel_filter import kernel_filter as filter_torch  # noqa: E402
from service.layout import KPN_FINE_OUTPUTS, KPN_INPUTS, groups_to_json, pad_planes  # noqa: E402
from service.runtime import METADATA_KEY, OnnxModel  # noqa: E402
from service.stages.kernel_filter import kernel_filter as filter_served  # noqa: E402
from tests.tolerances import ORT_ATOL  # noqa: E402


def random_heads(net):
    """Heads that are not the untrained zero: kernels and weights that differ per pixel and per step."""
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for head in (net.fine_head, net.half_head, net.quarter_head):
            head.weight.normal_(0.0, 0.3, generator=gen)
            head.bias.normal_(0.0, 0.3, generator=gen)
    return net


@pytest.fixture(scope="module")
def exported():
    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10)), seed=5)).eval()
    return net, export_bytes(net, extra={"training": {"options": {"motion": "plain"}}})


@pytest.mark.parametrize("size", [(13, 17), (1, 1), (37, 9)])
def test_torch_and_onnxruntime_agree_over_recurrent_steps(exported, size):
    net, model_bytes = exported
    model = OnnxModel(model_bytes, swappable=False)
    info = model.info
    rng = np.random.default_rng(size[0])
    h, w = size
    previous_np = previous_t = None
    for _step in range(3):
        planes = rng.standard_normal((8, h, w)).astype(np.float32)
        planes[:3] = np.abs(planes[:3])  # log1p radiance >= 0
        if previous_np is None:  # a sequence's first frame: the noisy radiance
            previous_np, previous_t = planes[:3], torch.from_numpy(planes[:3].copy())
        features = pad_planes(np.concatenate([planes, previous_np]), info.alignment)
        out = model.run({info.input_name: features[None]})
        served = filter_served(features[:3], features[8:], out["fine"][0], out["half"][0], out["quarter"][0],
                               space_to_depth=info.metadata["space_to_depth"])
        with torch.no_grad():
            feats_t = pad_planes(np.concatenate([planes, previous_t.numpy()]), net.alignment)
            fine, half, quarter = net(torch.from_numpy(feats_t[None]))
            ours = filter_torch(torch.from_numpy(feats_t[None, :3]), torch.from_numpy(feats_t[None, 8:]),
                                fine, half, quarter, space_to_depth=2)[0]
        for name, ref in zip(("fine", "half", "quarter"), (fine, half, quarter), strict=True):
            np.testing.assert_allclose(out[name], ref.numpy(), atol=ORT_ATOL, rtol=1e-4, err_msg=name)
        np.testing.assert_allclose(served, ours.numpy(), atol=ORT_ATOL, rtol=1e-4)
        previous_np, previous_t = served[:, :h, :w], ours[:, :h, :w]


def test_metadata_contract(exported):
    net, model_bytes = exported
    assert [p.key for p in onnx.load_from_string(model_bytes).metadata_props] == [METADATA_KEY]
    info = OnnxModel(model_bytes).info
    assert info.network == "kpn" and info.alignment == net.alignment == 8
    assert info.input_name == "features" and info.output_name == "fine"
    assert info.metadata["inputs"]["features"] == groups_to_json(KPN_INPUTS)
    assert info.metadata["outputs"]["fine"] == groups_to_json(KPN_FINE_OUTPUTS)
    assert [(c["output"], c["scale"]) for c in info.metadata["coarse"]] == list(COARSE_OUTPUTS)
    assert info.metadata["space_to_depth"] == 2
    assert info.metadata["motion"] == "plain" and info.metadata["config"]["widths"] == [6, 8, 10]
    assert json.loads(json.dumps(info.metadata)) == info.metadata


def test_manifest_command_keeps_the_step_the_occlusion_term_joined():
    """A run of 5,500 steps stopped at 4,434: its occlusion term joined at step 2,750, and so must the remake's."""
    from export.checkpoint import train_command

    command = train_command({"net": "kpn", "steps": 5500, "occlusion_from": 0.5, "motion": "dual",
                             "temporal_weight": 0.1}, 4434)
    share = float(command.split("--occlusion-from ")[1].split()[0])
    assert "--steps 4434" in command and round(share * 4434) == 2750 and "--temporal-weight" not in command
    rae = train_command({"net": "rae", "steps": 500, "occlusion_from": 0.5, "motion": "dual", "batch": 4,
                         "temporal_weight": 0.3}, 500)
    assert "--occlusion-from" not in rae and "--motion" not in rae and "--batch 4" in rae
    assert "--temporal-weight 0.3" in rae


def test_a_command_names_paths_in_the_working_directory_relative_to_it(tmp_path, monkeypatch):
    from export.checkpoint import train_command

    monkeypatch.chdir(tmp_path)
    inside, outside = str(tmp_path / "data" / "train"), "/elsewhere/val"
    command = train_command({"net": "rae", "data": inside, "val": outside, "init": str(tmp_path / "a" / "best.pt")}, 10)
    assert "--data data/train " in command and "--val /elsewhere/val " in command
    assert command.endswith("--init a/best.pt")
