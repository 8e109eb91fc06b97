"""The online worker seen from the serving side: it trains and publishes, a lagging worker drops frames
instead of delaying them, a crashed worker is reported and never raises into inference."""

import os
import signal
import time

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from export.crossreg_unet import export_bytes  # noqa: E402
from models.nets.crossreg_unet import make_unet  # noqa: E402
from service import pipelines  # noqa: E402
from service.layout import CROSSREG_SAMPLE, total_channels  # noqa: E402
from service.online import trainer as trainer_module  # noqa: E402
from service.online.trainer import OnlineConfig, OnlineTrainer, OnlineUnavailableError, random_crop  # noqa: E402

WORKER_START_S = 90  # spawning a process that imports torch, on 2 busy cores
N_SAMPLE = total_channels(CROSSREG_SAMPLE)


@pytest.fixture(scope="module")
def model_bytes():
    return export_bytes(make_unet(seed=0))


def _sample(seed, height=13, width=17):
    sample = np.random.default_rng(seed).random((height, width, N_SAMPLE), np.float32)
    sample[..., 15] = 1.0
    return sample


def _wait(predicate, trainer, published=None, timeout=WORKER_START_S):
    """Poll until predicate(published) holds; `published` collects every (version, weights) polled."""
    published = [] if published is None else published
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = trainer.poll()
        if got is not None:
            published.append(got)
        if predicate(published):
            return published
        time.sleep(0.05)
    raise AssertionError(f"timed out; status {trainer.status()}")


def test_lagging_worker_drops_frames_then_trains_publishes_and_reports_its_crash(model_bytes):
    """One worker (each costs seconds of torch import): lag, training, publication, exception."""
    trainer = OnlineTrainer(model_bytes, None, OnlineConfig(publish_every=2, crop=8, inbox_frames=2))
    try:
        # 1. lag: the worker is still importing torch; 20 frames in a row never wait for it
        start = time.perf_counter()
        accepted = [trainer.submit(_sample(i, 64, 64), i) for i in range(20)]
        assert time.perf_counter() - start < 2.0
        assert sum(accepted) == 2 and trainer.frames_dropped == 18
        assert trainer.status()["lagging"] and trainer.status()["running"]
        # 2. the two queued frames are trained later; the second completes a publication (K = 2)
        published = _wait(lambda p: trainer.frames_trained == 2 and len(p) == 1, trainer)
        version, weights = published[0]
        assert version == 1 and set(weights) == {k for k, _ in make_unet().named_parameters()}
        assert all(np.isfinite(w).all() for w in weights.values())
        assert [f for f, _ in trainer.losses] == [0, 1]
        assert trainer.submit(_sample(99), 99) and trainer.status()["state"] == "running"
        deadline = time.monotonic() + 30
        while trainer.status()["frames_trained"] < 3:  # status() reads progress only
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert trainer.submit(_sample(98), 98)
        while trainer.status()["weights_published"] < 2:  # frame 4 completes publication 2
            assert time.monotonic() < deadline
            time.sleep(0.05)
        status = trainer.status()
        assert status["frames_trained"] == 4 and status["frames_dropped"] == 18
        assert trainer.poll()[0] == 2 and trainer.poll() is None  # status() left the weights for poll()
        # 3. an exception in the worker: reported with its traceback, nothing raised here
        trainer.submit(np.zeros((8, 8, 5), np.float32), 100)  # 5 channels: the network wants 15
        _wait(lambda _: "Traceback" in (trainer.status()["last_error"] or ""), trainer, published)
        assert trainer.status()["crashed"]
        assert trainer.submit(_sample(0), 101) is False and trainer.frames_dropped == 19
    finally:
        trainer.close()
    assert trainer.status()["state"] == "stopped"


def test_a_killed_worker_is_reported_and_submit_keeps_working(model_bytes):
    trainer = OnlineTrainer(model_bytes, None, OnlineConfig(crop=8))
    try:
        _wait(lambda _: trainer.status()["state"] != "starting", trainer)
        os.kill(trainer.pid, signal.SIGKILL)
        _wait(lambda _: trainer.status()["crashed"], trainer, timeout=10)
        status = trainer.status()
        assert status["state"] == "crashed" and "exited with code -9" in status["last_error"]
        assert trainer.submit(_sample(0), 0) is False and trainer.poll() is None
    finally:
        trainer.close()


def test_missing_torch_gives_a_clear_error(monkeypatch, model_bytes):
    real = trainer_module.importlib.util.find_spec
    monkeypatch.setattr(
        trainer_module.importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a)
    )
    with pytest.raises(OnlineUnavailableError, match="online training needs torch"):
        OnlineTrainer(model_bytes)


@pytest.mark.parametrize("size, crop, expected", [((13, 17), 8, (8, 8)), ((13, 17), 0, (12, 16)), ((3, 2), 8, (4, 4))])
def test_random_crop_sizes_follow_the_alignment(size, crop, expected):
    out = random_crop(np.ones((*size, 22), np.float32), crop, 4, np.random.default_rng(0))
    assert out.shape == (*expected, 22)


def test_bad_online_options_are_refused():
    with pytest.raises(ValueError, match="publish_every must be >= 1"):
        OnlineConfig(publish_every=0)
    with pytest.raises(ValueError, match="crop must be >= 0"):
        OnlineConfig(crop=-1)
    with pytest.raises(ValueError, match=r"min_alpha must be in \[0, 1\]"):
        OnlineConfig(min_alpha=1.5)


def test_the_pipeline_hands_its_floor_to_the_worker():
    pipeline = pipelines.get("crossreg", min_alpha=0.6, pilot_bandwidth=8.0)
    assert pipeline._online_config.min_alpha == 0.6  # the worker trains through the filter that is served
    assert not hasattr(pipeline._online_config, "pilot_bandwidth")  # served only (models/train/step.py)
