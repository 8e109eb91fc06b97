"""The online fine-tuning worker: a torch process that trains the crossreg U-Net on the frames a serving
session sends, and publishes its weights every K frames (Choi et al. 2024, sec. 4.3).

Started by service/online/trainer.py with multiprocessing `spawn`; protocol on two queues:
  inbox  <- (frame_index, sample (h, w, 22) float32 in service.layout.CROSSREG_SAMPLE order) | None (stop)
  outbox -> ("ready", {...}) once, ("trained", {frame_index, frames, loss}) per frame,
            ("weights", {version, frames, loss, weights: name -> float32 array}) every `publish_every`
            frames, ("error", traceback text) before exiting on an exception.
The worker starts from the weights the serving session runs (the ONNX file's initializers, or the random
initialisation the session swapped in), so the two sides agree on the starting point. It does not judge
its own weights: the serving side refuses non-finite ones.
"""

from __future__ import annotations

import traceback
from typing import Any

import numpy as np


def run(
    inbox: Any, outbox: Any, config: dict[str, Any], model_bytes: bytes, weights: dict[str, np.ndarray] | None
) -> None:
    """Worker main loop (see module docstring); returns on the stop sentinel. Starts from `weights`, or
    when None from the initializers of the ONNX model `model_bytes` (the serving session's)."""
    try:
        import torch

        from export.onnx import initializers
        from models.nets.crossreg_unet import make_unet
        from models.train.step import (
            load_weights_numpy,
            make_optimizer,
            samples_to_tensor,
            train_step,
            weights_numpy,
        )

        torch.set_num_threads(int(config["worker_threads"]))
        net = make_unet()
        if weights is None:
            names = dict(net.named_parameters())
            weights = {k: v for k, v in initializers(model_bytes).items() if k in names}
        load_weights_numpy(net, weights)
        optimizer = make_optimizer(net, float(config["learning_rate"]))
        outbox.put(("ready", {"parameters": sum(p.numel() for p in net.parameters())}))
        frames = 0
        while True:
            item = inbox.get()
            if item is None:
                return
            frame_index, sample = item
            batch = samples_to_tensor(sample)
            for _ in range(int(config["steps_per_frame"])):
                loss = train_step(net, optimizer, batch, float(config["min_alpha"]))
            frames += 1
            outbox.put(("trained", {"frame_index": int(frame_index), "frames": frames, "loss": loss}))
            if frames % int(config["publish_every"]) == 0:
                version = frames // int(config["publish_every"])
                payload = {"version": version, "frames": frames, "loss": loss, "weights": weights_numpy(net)}
                outbox.put(("weights", payload))
    except BaseException:  # report anything, then die: the serving side keeps its last good weights
        outbox.put(("error", traceback.format_exc(limit=8)))
        raise
