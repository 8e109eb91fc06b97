"""The training ground on the bundled sample: windows as the paper samples them, the training CLI's files,
an exact resume, and validation scores on the benchmark's metrics."""

import csv
import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.data import SAMPLE_DIRS  # noqa: E402
from models.train.dataset import (  # noqa: E402
    SequenceBank,
    _rotate_motion,
    collate,
    load_sequence,
)
from models.train.train import BEST, CHECKPOINT, CURVES, LOG, LOG_FIELDS, TrainOptions, learning_rate, train  # noqa: E402
from service.exr import read_sequence  # noqa: E402
from service.stages.rae_inputs import GUIDE_PLANES, ROUGHNESS_ABSENT, demodulated  # noqa: E402

SAMPLE = SAMPLE_DIRS[0]


@pytest.fixture(scope="module")
def bank():
    return SequenceBank([load_sequence(SAMPLE)])


def test_sequences_lose_their_emission_and_albedo_as_the_pipeline_splits_them(bank):
    seq = bank.sequences[0]
    frame = next(iter(read_sequence(SAMPLE)))[1]
    expected = demodulated(frame["reference"] - frame["emission"], frame["albedo"]).transpose(2, 0, 1)
    np.testing.assert_allclose(seq.target[0], expected, rtol=1e-6)
    assert seq.noisy.shape == (3, 8, 3, 120, 120) and seq.guides.shape == (8, 5, 120, 120)


def test_windows_are_consecutive_frames_of_one_square_crop(bank):
    """Guides tagged with each pixel's frame, row and column: every window is T consecutive frames (either
    way) of one crop that lies within the sequence, turned as a whole."""
    seq = bank.sequences[0]
    f, _, h, w = seq.guides.shape
    tags = np.zeros_like(seq.guides)
    tags[:, :3] = np.indices((f, h, w), np.float32).transpose(1, 0, 2, 3)
    tagged = SequenceBank([dataclasses.replace(seq, guides=tags)])
    rng = np.random.default_rng(0)
    windows = [tagged.sample(rng, 7, 96) for _ in range(8)]
    batch = collate(windows)
    assert batch.noisy.shape == (8, 7, 3, 96, 96) and batch.guides.shape == (8, 7, 5, 96, 96)
    assert batch.motion.shape == (8, 7, 2, 96, 96)
    for window in windows:
        frame, row, column = window.guides[:, :3].numpy().transpose(1, 0, 2, 3)
        assert (frame == frame[:, :1, :1]).all() and abs(np.diff(frame[:, 0, 0])).tolist() == [1] * 6
        assert (row == row[:1]).all() and (column == column[:1]).all()  # the same crop in every frame
        rows, columns = np.unique(row), np.unique(column)
        assert len(rows) == len(columns) == 96 and (np.diff(rows) == 1).all() and (np.diff(columns) == 1).all()
        assert 0 <= min(rows[0], columns[0]) and rows[-1] < h and columns[-1] < w
        assert len(np.unique(row * w + column)) == 96 * 96  # every pixel of the crop once


def test_colour_modulation_is_one_factor_per_channel_for_noisy_and_target_alike(bank):
    seq = bank.sequences[0]
    ones = dataclasses.replace(seq, name="ones", noisy=np.ones_like(seq.noisy), target=np.ones_like(seq.target))
    rng = np.random.default_rng(2)
    for _ in range(4):
        window = SequenceBank([ones]).sample(rng, 7, 96)
        scale = window.target[0, :, 0, 0]
        assert ((0 <= scale) & (scale <= 2)).all()
        assert torch.equal(window.target, scale.view(1, 3, 1, 1).expand_as(window.target))
        assert torch.equal(window.noisy, window.target)


def test_some_windows_see_no_roughness(bank):
    rng = np.random.default_rng(3)
    dropped = [bool((bank.sample(rng, 7, 96).guides[:, GUIDE_PLANES["roughness"]] == ROUGHNESS_ABSENT).all())
               for _ in range(40)]
    assert 0 < sum(dropped) < 40


def test_forward_only_windows_keep_their_motion(bank):
    rng = np.random.default_rng(1)
    moving = [bank.sample(rng, 7, 96, reverse=False) for _ in range(4)]
    assert all(w.motion.abs().max() > 0 for w in moving)


def test_rotating_motion_with_the_image_keeps_it_pointing_at_the_same_content():
    """A pixel that moved right (+x) moves up (-y) after a counter-clockwise quarter turn (torch.rot90)."""
    motion = torch.zeros((2, 4, 4))
    motion[0] = 1.0
    turned = _rotate_motion(motion, 1)
    assert (turned[0] == 0).all() and (turned[1] == -1).all()
    assert torch.equal(_rotate_motion(motion, 4), motion)


def test_with_warp_each_level_moves_by_the_motion_over_its_scale():
    """Every pixel was 4 px to the right: the state of scale 2 moves 2 columns, that of scale 4 one, and
    what comes from outside the frame is zero."""
    from models.nets.rae import RaeConfig, make_rae
    from models.train.rae import RaeRecipe

    net = make_rae(RaeConfig(widths=(4, 6)), seed=0).eval()
    features = torch.randn(1, 2, 8, 16, 16)
    motion = torch.zeros(1, 2, 2, 16, 16)
    motion[:, :, 0] = 4.0
    with torch.no_grad():
        out = RaeRecipe(warp=True).run(net, features, motion)
        _, *hidden = net(features[:, 0], *net.zero_hidden(1, 16, 16))
        moved = [torch.zeros_like(h) for h in hidden]
        for h, m, columns in zip(hidden, moved, (2, 1), strict=True):
            m[..., :-columns] = h[..., columns:]
        expected = net(features[:, 1], *moved)[0]
    torch.testing.assert_close(out[:, 1], expected)


def test_learning_rate_ramps_tenfold_then_falls_as_one_over_sqrt():
    assert learning_rate(0, 1e-3, 100) == pytest.approx(1e-4)
    assert learning_rate(100, 1e-3, 100) == pytest.approx(1e-3)
    assert learning_rate(400, 1e-3, 100) == pytest.approx(5e-4)


def _opts(tmp_path, steps, name="run"):
    return TrainOptions(net="rae", data=str(SAMPLE), val=str(SAMPLE), out=str(tmp_path / name), steps=steps,
                        batch=1, warmup=2, threads=1, val_every=2, log_every=1, checkpoint_every=2)


def test_training_writes_its_files_and_resumes_exactly(tmp_path):
    straight = train(_opts(tmp_path, 4, "straight"), progress=False)
    train(_opts(tmp_path, 2, "resumed"), progress=False)
    resumed = train(_opts(tmp_path, 4, "resumed"), resume=True, progress=False)
    assert straight["step"] == resumed["step"] == 4
    for name, value in straight["state_dict"].items():
        assert torch.equal(value, resumed["state_dict"][name]), name
    out = tmp_path / "straight"
    assert all((out / f).is_file() for f in (CHECKPOINT, BEST, LOG, CURVES))
    rows = list(csv.DictReader((out / LOG).open()))
    val = [r for r in rows if r["kind"] == "val"]
    assert [int(r["step"]) for r in val] == [2, 4]
    assert all(np.isfinite(float(r["val_rel_l2"])) and float(r["val_temporal"]) > 0 for r in val)
    assert len([r for r in rows if r["kind"] == "train"]) == 4


def test_resume_with_other_options_is_refused(tmp_path):
    train(_opts(tmp_path, 1), progress=False)
    changed = TrainOptions(**{**_opts(tmp_path, 2).__dict__, "lr": 5e-4})
    with pytest.raises(ValueError, match=r"other options than the run had .*lr 0.001 -> 0.0005"):
        train(changed, resume=True, progress=False)


def test_resume_without_a_checkpoint_says_so(tmp_path):
    with pytest.raises(FileNotFoundError, match="no .*checkpoint.pt"):
        train(_opts(tmp_path, 2), resume=True, progress=False)


def test_options_are_validated():
    with pytest.raises(ValueError, match="unknown network 'nope'"):
        TrainOptions(net="nope", data="d", val="v", out="o")
    with pytest.raises(ValueError, match="steps must be >= 1"):
        TrainOptions(net="rae", data="d", val="v", out="o", steps=0)
    with pytest.raises(ValueError, match="device must be one of cpu, cuda, got 'tpu'"):
        TrainOptions(net="rae", data="d", val="v", out="o", device="tpu")
    for bad in (0.0, 2.0):
        with pytest.raises(ValueError, match="tone_eps must be in"):
            TrainOptions(net="rae", data="d", val="v", out="o", tone_eps=bad)
    for bad in (-0.1, 0.95):
        with pytest.raises(ValueError, match="temporal_weight must be in"):
            TrainOptions(net="rae", data="d", val="v", out="o", temporal_weight=bad)
    for net in ("kpn", "flnr"):
        with pytest.raises(ValueError, match="--temporal-weight is rae's"):
            TrainOptions(net=net, data="d", val="v", out="o", temporal_weight=0.3)


def test_the_runs_temporal_weight_reaches_raes_loss():
    from models.train.rae_loss import WEIGHTS
    from models.train.train import make_recipe

    assert make_recipe(TrainOptions(net="rae", data="d", val="v", out="o")).weights == pytest.approx(WEIGHTS)
    recipe = make_recipe(TrainOptions(net="rae", data="d", val="v", out="o", temporal_weight=0.4))
    assert recipe.weights == pytest.approx((0.5, WEIGHTS[1], 0.4))


@pytest.mark.parametrize("net", ["rae", "flnr", "kpn"])
def test_every_recipe_takes_the_runs_tone_eps(net, bank):
    """The run's tone eps reaches each recipe's loss: against a black target the loss is the mean of
    (p + eps)^0.2 - eps^0.2, which differs between two eps."""
    from models.train.rae_loss import TONE_EPS
    from models.train.train import make_recipe

    assert make_recipe(TrainOptions(net=net, data="d", val="v", out="o")).tone_eps == TONE_EPS
    losses = []
    for eps in (TONE_EPS, 0.01):
        recipe = make_recipe(TrainOptions(net=net, data="d", val="v", out="o", tone_eps=eps))
        assert recipe.tone_eps == eps
        window = bank.sample(np.random.default_rng(0), recipe.frames, recipe.crop, reverse=recipe.reverse)
        batch = collate([window])
        batch = dataclasses.replace(batch, target=torch.zeros_like(batch.target))
        losses.append(float(recipe.loss(recipe.build(0), batch).spatial.detach()))
    assert losses[0] > 1.2 * losses[1] > 0  # the steeper power near black costs more


def test_best_checkpoint_keeps_only_what_export_and_fine_tuning_read(tmp_path):
    train(_opts(tmp_path, 2), progress=False)
    best = torch.load(tmp_path / "run" / BEST, map_location="cpu", weights_only=False)
    assert "optimizer" not in best and "state_dict" not in best
    assert {"config", "ema_state_dict", "options", "step", "data", "val", "machine"} <= set(best)


def test_a_fine_tune_starts_from_the_weights_its_checkpoint_serves_with(tmp_path):
    from models.train.rae import RaeRecipe
    from models.train.train import _start, inference_state

    train(_opts(tmp_path, 2), progress=False)
    served = inference_state(torch.load(tmp_path / "run" / BEST, map_location="cpu", weights_only=False))
    opts = TrainOptions(**{**_opts(tmp_path, 4, "tuned").__dict__, "init": str(tmp_path / "run" / BEST)})
    net, ema, _optimizer, step, *_ = _start(opts, RaeRecipe(), tmp_path / "tuned" / CHECKPOINT, resume=False)
    assert step == 0
    for name, value in served["state_dict"].items():
        assert torch.equal(net.state_dict()[name], value) and torch.equal(ema.state_dict()[name], value), name


def test_export_writes_the_model_and_a_manifest_of_how_it_was_made(tmp_path):
    pytest.importorskip("onnx")
    import json

    from export.checkpoint import export_checkpoint
    from service.pipelines.rae import trained_with_warp
    from service.runtime import OnnxModel

    train(_opts(tmp_path, 2), progress=False)
    path = export_checkpoint("rae", tmp_path / "run" / BEST, tmp_path / "weights" / "rae.onnx")
    info = json.loads(path.with_suffix(".json").read_text())
    assert info["step"] == 2 and info["seed"] == 0 and info["data"] == [SAMPLE.name]
    assert info["commands"][1].startswith("python -m models.train rae --data ") and len(info["commands"]) == 3
    script = "models/train/accelerator.sh OUT 130 5.0 8"  # a run whose data that script rendered
    made = export_checkpoint("rae", tmp_path / "run" / BEST, tmp_path / "weights" / "rae.onnx", made_by=script)
    commands = json.loads(made.with_suffix(".json").read_text())["commands"]
    assert commands[:2] == [script, info["commands"][1]]  # its data came from the script, not `make data`
    assert commands[2] == f"{info['commands'][2]} --made-by '{script}'" and len(commands) == 3
    assert info["machine"]["device"] == "cpu" and info["final_train_loss"]["loss"] > 0
    assert [v["step"] for v in info["validation_curve"]] == [2]
    model = OnnxModel.from_file(path, swappable=False)
    assert model.info.network == "rae" and not trained_with_warp(model)


def test_a_manifest_names_what_made_each_run_of_a_fine_tune_chain(tmp_path):
    """A fine-tune of a run whose data a script rendered: `make data` for the fine-tune's data, the script
    before the run it made, then each run's command, oldest first; a checkpoint outside the chain is refused."""
    pytest.importorskip("onnx")
    import json

    from export.checkpoint import export_checkpoint

    train(_opts(tmp_path, 2, "first"), progress=False)
    first = str(tmp_path / "first" / BEST)
    tuned = dataclasses.replace(_opts(tmp_path, 2, "tuned"), init=first, tone_eps=0.01)
    train(tuned, progress=False)
    script = "INIT_rae=x NETS=rae models/train/accelerator.sh OUT 130 5.0 8"
    out = tmp_path / "weights" / "rae.onnx"
    path = export_checkpoint("rae", tmp_path / "tuned" / BEST, out, earlier={first: script})
    commands = json.loads(path.with_suffix(".json").read_text())["commands"]
    assert commands[0] == "make data" and commands[1] == script and len(commands) == 5
    assert commands[2].startswith("python -m models.train rae ") and "--init" not in commands[2]
    assert f"--init {first}" in commands[3] and "--tone-eps 0.01" in commands[3]
    assert commands[4].endswith(f"--made-by-for {first} '{script}'")
    with pytest.raises(ValueError, match="--made-by-for names no checkpoint"):
        export_checkpoint("rae", tmp_path / "tuned" / BEST, out, earlier={"elsewhere/best.pt": script})


def test_a_fine_tune_of_exported_weights_starts_from_them_and_its_manifest_starts_with_theirs(tmp_path):
    """`--init models/weights/NET.onnx`: the network the ONNX file holds, parameter for parameter, and the
    manifest of the fine-tune lists the commands that made those weights (from the manifest beside them)
    before its own; exported weights without a manifest are refused, as a file that is no export is."""
    pytest.importorskip("onnx")
    import json

    from export.checkpoint import export_checkpoint
    from models.train.rae import RaeRecipe
    from models.train.train import _start, inference_state

    train(_opts(tmp_path, 2, "first"), progress=False)
    shipped = export_checkpoint("rae", tmp_path / "first" / BEST, tmp_path / "weights" / "rae.onnx")
    served = inference_state(torch.load(tmp_path / "first" / BEST, map_location="cpu", weights_only=False))
    tuned = dataclasses.replace(_opts(tmp_path, 2, "tuned"), init=str(shipped))
    net, _ema, _optimizer, step, *_ = _start(tuned, RaeRecipe(), tmp_path / "tuned" / CHECKPOINT, resume=False)
    assert step == 0 and set(net.state_dict()) == set(served["state_dict"])
    for name, value in served["state_dict"].items():
        assert torch.equal(net.state_dict()[name], value), name
    train(tuned, progress=False)
    made = json.loads(shipped.with_suffix(".json").read_text())
    train(dataclasses.replace(tuned, steps=3), resume=True, progress=False)  # a resumed run keeps it too
    resumed = torch.load(tmp_path / "tuned" / CHECKPOINT, map_location="cpu", weights_only=False)
    assert resumed["step"] == 3 and resumed["init_manifest"] == made
    for _ in range(2):  # exported over the weights it started from, twice: the chain stays as it was
        path = export_checkpoint("rae", tmp_path / "tuned" / BEST, shipped)
        info = json.loads(path.with_suffix(".json").read_text())
        assert info["commands"][:3] == made["commands"] and len(info["commands"]) == 5
        assert f"--init {shipped}" in info["commands"][3] and info["commands"][4].startswith("python -m export rae ")
        assert info["fine_tuned_from"][0]["step"] == 2 and info["fine_tuned_from"][0]["onnx"] == str(shipped)
    shipped.with_suffix(".json").unlink()
    with pytest.raises(ValueError, match="no manifest rae.json beside it"):
        train(dataclasses.replace(tuned, out=str(tmp_path / "again")), progress=False)
    (tmp_path / "not_exported.onnx").write_bytes(b"")  # parses as an empty model, without our metadata
    with pytest.raises(ValueError, match="not a model this project exported"):
        _start(dataclasses.replace(tuned, init=str(tmp_path / "not_exported.onnx")), RaeRecipe(),
               tmp_path / "x" / CHECKPOINT, resume=False)


def test_the_three_commands_chain(tmp_path, capsys):
    """`python -m models.train` then `python -m export`, as docs/training.md gives them."""
    pytest.importorskip("onnx")
    from export.__main__ import main as export_main
    from models.train.__main__ import main as train_main

    out = tmp_path / "run"
    assert train_main(["rae", "--data", str(SAMPLE), "--val", str(SAMPLE), "--out", str(out), "--steps", "1",
                       "--batch", "1", "--threads", "1"]) == 0
    assert "best held-out relL2" in capsys.readouterr().out
    assert export_main(["rae", str(out / BEST), str(tmp_path / "rae.onnx")]) == 0
    assert (tmp_path / "rae.onnx").is_file() and (tmp_path / "rae.json").is_file()
    with pytest.raises(SystemExit, match="steps must be >= 1"):
        train_main(["rae", "--data", "d", "--val", "v", "--out", "o", "--steps", "0"])


def test_a_resumed_run_keeps_options_its_checkpoint_predates(tmp_path):
    """A checkpoint written before an option existed ran with its default: resuming with another value is
    refused, as for any stored option."""
    train(_opts(tmp_path, 2), progress=False)
    path = tmp_path / "run" / "checkpoint.pt"
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    del ckpt["options"]["clip_grad"]
    torch.save(ckpt, path)
    with pytest.raises(ValueError, match="clip_grad 0.0 -> 0.5"):
        train(TrainOptions(**{**_opts(tmp_path, 4).__dict__, "clip_grad": 0.5}), resume=True, progress=False)
    assert train(_opts(tmp_path, 3), resume=True, progress=False)["step"] == 3


def test_a_run_holds_torch_and_numba_to_its_threads_and_gives_them_back(tmp_path, monkeypatch):
    """Side-by-side runs share the cores: each step's torch and numba (flnr's firefly clamp is a numba
    kernel) use the run's --threads, and the process has its own counts back after."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here: a run's count of 1 would be its default")
    seen = []
    adam_step = torch.optim.Adam.step

    def spy(self, *args, **kwargs):
        seen.append((torch.get_num_threads(), numba.get_num_threads()))
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)
    saved = torch.get_num_threads(), numba.get_num_threads()
    try:
        torch.set_num_threads(2)
        numba.set_num_threads(2)
        train(_opts(tmp_path, 2), progress=False)  # threads=1
        assert seen == [(1, 1), (1, 1)]
        assert (torch.get_num_threads(), numba.get_num_threads()) == (2, 2)
    finally:
        torch.set_num_threads(saved[0])
        numba.set_num_threads(saved[1])
    with pytest.raises(ValueError, match="threads must be >= 0"):
        TrainOptions(**{**_opts(tmp_path, 2).__dict__, "threads": -1})


def test_clip_grad_bounds_the_gradient_norm_each_step_applies(tmp_path, monkeypatch):
    """The optimiser sees gradients of global norm at most --clip-grad; without it, larger ones (so the bound
    is not met by chance)."""
    seen = []
    adam_step = torch.optim.Adam.step

    def spy(self, *args, **kwargs):
        grads = [p.grad for group in self.param_groups for p in group["params"] if p.grad is not None]
        seen.append(float(torch.nn.utils.get_total_norm(grads)))
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)
    train(_opts(tmp_path, 2, "free"), progress=False)
    assert len(seen) == 2 and min(seen) > 1e-3
    seen.clear()
    train(TrainOptions(**{**_opts(tmp_path, 2, "clipped").__dict__, "clip_grad": 1e-3}), progress=False)
    assert len(seen) == 2 and max(seen) <= 1e-3 * (1 + 1e-5)
    with pytest.raises(ValueError, match="clip_grad must be in"):
        TrainOptions(**{**_opts(tmp_path, 2).__dict__, "clip_grad": -1.0})


def test_weight_average_follows_the_weights_and_is_what_a_checkpoint_serves():
    from models.nets.rae import RaeConfig, make_rae
    from models.train.train import inference_state, update_average

    net, ema = make_rae(RaeConfig(widths=(4,)), seed=0), make_rae(RaeConfig(widths=(4,)), seed=1)
    update_average(ema, net, 0.0, step=100)  # decay 0: a copy
    assert all(torch.equal(a, b) for a, b in zip(ema.parameters(), net.parameters(), strict=True))
    before = [p.clone() for p in ema.parameters()]
    with torch.no_grad():
        for p in net.parameters():
            p.add_(1.0)
    update_average(ema, net, 0.9, step=1000)  # d = 0.9: a tenth of the way
    for old, new in zip(before, ema.parameters(), strict=True):
        torch.testing.assert_close(new, old + 0.1)
    ckpt = {"config": {}, "state_dict": {"w": 1}, "ema_state_dict": {"w": 2}}
    assert inference_state(ckpt)["state_dict"] == {"w": 2}
    assert inference_state({"config": {}, "state_dict": {"w": 1}})["state_dict"] == {"w": 1}


def test_kpn_trains_with_the_occlusion_term_from_its_step_and_windows_carry_motion_dual(tmp_path, bank):
    """`--occlusion-from 0.5` of 4 steps: the logged total is spatial + temporal for steps 1-2 and adds the
    occlusion term from step 3; the windows' dual motion differs from the motion somewhere (the sample has
    moving occluders)."""
    rng = np.random.default_rng(4)
    windows = [bank.sample(rng, 7, 64, reverse=False) for _ in range(6)]
    assert any((w.motion_dual != w.motion).any() for w in windows)
    opts = TrainOptions(**{**_opts(tmp_path, 4, "kpn").__dict__, "net": "kpn", "occlusion_from": 0.5})
    train(opts, progress=False)
    rows = [r for r in csv.DictReader((tmp_path / "kpn" / LOG).open()) if r["kind"] == "train"]
    assert len(rows) == 4 and all(float(r["occlusion"]) > 0 for r in rows)  # seed 0's windows show occlusions
    for row in rows:
        terms = float(row["spatial"]) + float(row["temporal"])
        occlusion = float(row["occlusion"]) if int(row["step"]) > 2 else 0.0
        assert float(row["loss"]) == pytest.approx(terms + occlusion, rel=1e-5), row["step"]
    with pytest.raises(ValueError, match="--motion is kpn's"):
        TrainOptions(**{**_opts(tmp_path, 4).__dict__, "motion": "plain"})
    with pytest.raises(ValueError, match="--occlusion-from is kpn's"):
        TrainOptions(**{**_opts(tmp_path, 4).__dict__, "occlusion_from": 0.25})
    with pytest.raises(ValueError, match="kpn always warps"):
        train(TrainOptions(**{**opts.__dict__, "warp": True}), progress=False)


def test_a_log_from_an_older_version_keeps_its_columns_when_a_resumed_run_appends(tmp_path):
    """A log.csv whose header lacks a field (written before `occlusion` existed) gets rows under its own
    header, so every value stays under its name."""
    from models.train.train import _append_log

    path = tmp_path / LOG
    old = [f for f in LOG_FIELDS if f != "occlusion"]
    path.write_text(",".join(old) + "\n")
    _append_log(path, {"step": 7, "kind": "val", "occlusion": 0.5, "val_rel_l2": 0.125, "lr": 0.001})
    (row,) = list(csv.DictReader(path.open()))
    assert list(row) == old
    assert row["step"] == "7" and row["val_rel_l2"] == "0.125" and row["lr"] == "0.001"
