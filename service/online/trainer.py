"""Serving side of online fine-tuning: a torch worker process that trains the crossreg U-Net while a
sequence streams, and hands back new weights (Choi et al. 2024, sec. 4.3: one Adam step per frame).

    trainer = OnlineTrainer(model_bytes, None, OnlineConfig(publish_every=4, crop=128))
    trainer.submit(sample, frame_index)      # never blocks: a full inbox drops the frame from training
    trainer.submit(sample, frame_index, wait=300.0)   # lockstep: returns once the worker trained on it
    weights = trainer.poll()                 # newest published weights, or None; never blocks
    trainer.status()                         # running / lagging / crashed, counters, weights version

The worker (models/train/online_worker.py) runs in a separate process started with the multiprocessing
`spawn` method; this module imports neither torch nor models/ (the child imports them). Samples travel
through a bounded multiprocessing queue as random crops (`crop` pixels a side) of the frame's
(H, W, 22) training sample (service.layout.CROSSREG_SAMPLE): a crop keeps a CPU training step in the
tens of milliseconds and the pickled message small, at the price of training on a part of each frame
(over a sequence the crops cover the frame) and of a filter window cut at the crop edge.

Failure model: a worker that raises reports its traceback and exits; a worker that dies is seen by
`status()` through its exit code. Either way inference continues on the last weights the caller
accepted; the caller refuses non-finite weights (service.runtime.OnnxModel.swap_weights).
"""

from __future__ import annotations

import importlib
import importlib.util
import multiprocessing as mp
import queue
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

WORKER_MODULE = "models.train.online_worker"  # imported in the child process only
LOCKSTEP_POLL_S = 0.002  # how often a lockstep submit looks for the worker's answer, seconds


class OnlineUnavailableError(ValueError):
    """Online training was asked for but torch (the `train` extra) is not installed: an option value this
    installation cannot honour (a ValueError, so the CLI and the API report it as a bad option)."""


@dataclass(frozen=True)
class OnlineConfig:
    """Options of online fine-tuning (crossreg pipeline options of the same names)."""

    publish_every: int = 4  # K: frames trained between weight publications
    crop: int = 128  # side of the random training crop, pixels (0: the whole frame)
    steps_per_frame: int = 1  # gradient steps per received frame (Choi 2024: 1)
    learning_rate: float = 1e-3  # Adam (Choi 2024 sec. 4.4)
    inbox_frames: int = 2  # frames that may wait for the worker; more are dropped from training
    worker_threads: int = 1  # torch threads of the worker (leaves the other cores to inference)
    seed: int = 0  # crop positions
    alignment: int = 4  # crops are multiples of it (the network's, from the ONNX metadata)
    min_alpha: float = 0.0  # the served filter's floor of alpha, which training goes through too

    def __post_init__(self) -> None:
        for name in ("publish_every", "steps_per_frame", "inbox_frames", "worker_threads", "alignment"):
            if getattr(self, name) < 1:
                raise ValueError(f"online option {name} must be >= 1, got {getattr(self, name)}")
        if self.crop < 0:
            raise ValueError(f"online option crop must be >= 0 (0: whole frame), got {self.crop}")
        if not 0 <= self.min_alpha <= 1:
            raise ValueError(f"online option min_alpha must be in [0, 1], got {self.min_alpha}")
        if not self.learning_rate > 0:
            raise ValueError(f"online option learning_rate must be > 0, got {self.learning_rate}")


def require_torch() -> None:
    """Raise OnlineUnavailableError when torch cannot be imported."""
    if importlib.util.find_spec("torch") is None:
        raise OnlineUnavailableError(
            "online training needs torch, which is not installed; install the train extra "
            "(pip install 'mcdenoise[train]') or run without --online / online=false"
        )


def _child_main(
    inbox: Any, outbox: Any, config: dict[str, Any], model_bytes: bytes, weights: dict[str, np.ndarray] | None
) -> None:
    """Entry point of the spawned process: import the torch worker there, not here."""
    importlib.import_module(WORKER_MODULE).run(inbox, outbox, config, model_bytes, weights)


def random_crop(sample: np.ndarray, size: int, alignment: int, rng: np.random.Generator) -> np.ndarray:
    """A random window of `sample` (H, W, C) whose sides are `size` (or the frame's) cut down to multiples
    of `alignment`; a frame smaller than the alignment is edge-padded up to it. size 0: whole frame."""
    height, width = sample.shape[:2]
    if height < alignment or width < alignment:
        sample = np.pad(sample, ((0, max(0, alignment - height)), (0, max(0, alignment - width)), (0, 0)), "edge")
        height, width = sample.shape[:2]
    ch = min(size, height) if size > 0 else height
    cw = min(size, width) if size > 0 else width
    ch, cw = ch - ch % alignment, cw - cw % alignment
    y = int(rng.integers(0, height - ch + 1))
    x = int(rng.integers(0, width - cw + 1))
    return np.ascontiguousarray(sample[y : y + ch, x : x + cw], dtype=np.float32)


class OnlineTrainer:
    """Owns one worker process for one sequence. Not thread-safe: one caller (the pipeline step)."""

    def __init__(
        self,
        model_bytes: bytes,
        initial_weights: dict[str, np.ndarray] | None = None,
        config: OnlineConfig | None = None,
    ):
        """model_bytes: the ONNX model the serving session runs (graph and, unless `initial_weights` is
        given, the starting weights: its initializers). initial_weights: name -> float32 array to start
        from instead (e.g. a random initialisation the session also swapped in)."""
        require_torch()
        self.config = config or OnlineConfig()
        ctx = mp.get_context("spawn")
        self._inbox = ctx.Queue(maxsize=self.config.inbox_frames)
        self._outbox = ctx.Queue()
        self._rng = np.random.default_rng(self.config.seed)
        self.frames_submitted = 0
        self.frames_dropped = 0
        self.frames_trained = 0
        self.last_loss: float | None = None
        self.losses: list[tuple[int, float]] = []  # (frame index, loss before its step): the training curve
        self.published = 0  # weight sets received from the worker
        self.last_error: str | None = None
        self._ready = False
        self._failed = False
        self._pending: tuple[int, dict[str, np.ndarray]] | None = None
        self._last_dropped = False
        self._trained_index = -1  # frame index of the worker's latest "trained" message
        self._behind = False  # a lockstep wait timed out: later submits do not wait
        self._closed = False
        self._process = ctx.Process(
            target=_child_main,
            args=(self._inbox, self._outbox, asdict(self.config), model_bytes, initial_weights),
            name="crossreg-online-worker",
            daemon=True,
        )
        self._process.start()
        # The worker's messages are read by a daemon thread into a local queue, so `poll` never blocks:
        # a worker killed in the middle of writing a message would leave a reader waiting forever.
        self._messages: queue.SimpleQueue = queue.SimpleQueue()
        self._reader = threading.Thread(target=self._read_outbox, name="crossreg-online-reader", daemon=True)
        self._reader.start()

    def _read_outbox(self) -> None:
        while True:
            try:
                message = self._outbox.get(timeout=0.2)
            except queue.Empty:
                if self._closed or not self._process.is_alive():
                    return
                continue
            except (EOFError, OSError, ValueError):  # closed, or the worker's end is gone
                return
            self._messages.put(message)

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def alive(self) -> bool:
        return self._process.is_alive() and not self._failed

    def submit(self, sample: np.ndarray, frame_index: int, *, wait: float = 0.0) -> bool:
        """Offer one frame's training sample (H, W, 22) float32; returns False when it was dropped (worker
        busy or gone). With wait 0 it never blocks: cropping and one non-blocking put. With wait > 0 (seconds;
        lockstep, Choi 2024's one step per frame) it waits for room in the inbox, then until the worker has
        trained on this frame and sent any weights due after it (`poll` returns them); a timeout or a dead
        worker counts as a drop, and after one timeout later calls no longer wait (the worker is behind)."""
        self.frames_submitted += 1
        wait = 0.0 if self._behind else wait
        if self._closed or not self.alive():
            return self._dropped()
        crop = random_crop(sample, self.config.crop, self.config.alignment, self._rng)
        deadline = time.monotonic() + wait
        try:
            if wait > 0:
                self._inbox.put((frame_index, crop), timeout=wait)
            else:
                self._inbox.put_nowait((frame_index, crop))
        except queue.Full:
            return self._dropped()
        if wait > 0 and not self._await_trained(frame_index, deadline):
            self._behind = True
            return self._dropped()
        self._last_dropped = False
        return True

    def _dropped(self) -> bool:
        self.frames_dropped += 1
        self._last_dropped = True
        return False

    def _await_trained(self, frame_index: int, deadline: float) -> bool:
        """Wait until the worker reported frame `frame_index` trained and every publication due by then has
        arrived; False on a failed or dead worker or at `deadline` (time.monotonic())."""
        while time.monotonic() < deadline:
            self._drain()
            if self._failed or not self._process.is_alive():
                return False
            due = self.frames_trained // self.config.publish_every
            if self._trained_index >= frame_index and self.published >= due:
                return True
            time.sleep(LOCKSTEP_POLL_S)
        return False

    def _drain(self) -> None:
        """Take in every message the reader thread has received; keep the newest weights for `poll`."""
        while True:
            try:
                kind, payload = self._messages.get_nowait()
            except queue.Empty:
                return
            if kind == "ready":
                self._ready = True
            elif kind == "trained":
                self.frames_trained = payload["frames"]
                self._trained_index = payload["frame_index"]
                self.last_loss = payload["loss"]
                self.losses.append((payload["frame_index"], payload["loss"]))
            elif kind == "weights":
                self.published += 1
                self._pending = (payload["version"], payload["weights"])
            elif kind == "error":
                self.last_error = payload
                self._failed = True

    def poll(self) -> tuple[int, dict[str, np.ndarray]] | None:
        """(version, weights) of the newest set published since the last call, or None; never blocks."""
        self._drain()
        newest, self._pending = self._pending, None
        return newest

    def status(self) -> dict[str, Any]:
        """running / lagging / starting / crashed / stopped, with counters (see crossreg online_status).
        Reads the worker's progress messages but leaves published weights for `poll`."""
        self._drain()
        if self._closed:
            state = "stopped"
        elif self._failed or not self._process.is_alive():
            state = "crashed"
            if self.last_error is None:
                self.last_error = f"worker process exited with code {self._process.exitcode}"
        elif self._last_dropped:
            state = "lagging"  # the last frame offered was dropped: the worker is behind (or still starting)
        elif not self._ready:
            state = "starting"
        else:
            state = "running"
        return {
            "state": state,
            "running": state in ("starting", "running", "lagging"),
            "crashed": state == "crashed",
            "lagging": state == "lagging",
            "frames_submitted": self.frames_submitted,
            "frames_trained": self.frames_trained,
            "frames_dropped": self.frames_dropped,
            "weights_published": self.published,
            "last_loss": self.last_loss,
            "last_error": self.last_error,
            "pid": self._process.pid,
        }

    def close(self, timeout: float = 2.0) -> None:
        """Stop the worker (sentinel, then terminate after `timeout` seconds). Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._inbox.put_nowait(None)
        except (queue.Full, ValueError, OSError):
            pass
        deadline = time.monotonic() + timeout
        self._process.join(max(0.0, deadline - time.monotonic()))
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(1.0)
        for q in (self._inbox, self._outbox):
            q.cancel_join_thread()
            q.close()
