"""Evidence for the crossreg pipeline: error of every variant on the same frames, the online training
curve, and milliseconds per frame beside OIDN measured in the same run.

    python -m models.train.crossreg_evidence quality --sequence DIR --sequence synthetic:96x128x32 --out R.json
    python -m models.train.crossreg_evidence timing --sizes 256x256 1280x720 --repeats 3

Quality: relL2 and 1-SSIM (service.metrics), mean over the frames of each sequence, for noisy input,
cross-regression alone (mean of the two pilots), bmfr (when that pipeline is registered), crossreg on the
warm start without online training, online from random initialisation, warm start + online, and OIDN
high (pyoidn, with albedo and normal). The online variants here run with a worker that keeps up
(`--sync`, default): after each frame the script waits until the worker has trained on it, and K = 1,
so frame t + 1 runs on weights that saw frames <= t: the paper's setting (one step per frame on a GPU).
`--async` measures the real-time behaviour instead (frames dropped when the worker lags).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from service import pipelines
from service.exr import list_sequence, read_frame
from service.frame import Frame
from service.metrics import dssim, rel_l2
from service.pipelines.crossreg import prepare_frame
from service.process import configure
from service.stages.cross_regression import cross_regression, pilots_to_radiance
from service.stages.emission import subtract_emission

log = logging.getLogger("models.train.crossreg_evidence")

WAIT_S = 120.0  # longest wait for the worker to train one frame (sync mode; it starts by importing torch)


def _oidn(frame: Frame) -> np.ndarray:
    import pyoidn

    color = np.maximum(frame["color"], 0.0)
    return pyoidn.denoise(color, frame["albedo"], frame["normal"], hdr=True, quality="high")


def _pilots_alone(frame: Frame) -> np.ndarray:
    emission = frame.get("emission")
    if emission is not None:  # as the step splits it (`subtract_emission`, its clip at an emitter's edge)
        color_a, color_b = subtract_emission([frame["colorA"], frame["colorB"]], emission)
        frame = frame.replace(colorA=color_a, colorB=color_b)
    out = np.maximum(pilots_to_radiance(*cross_regression(frame["colorA"], frame["colorB"], frame["albedo"],
                                                          frame["normal"])), 0.0)  # fmt: skip
    return out + (emission if emission is not None else 0.0)


def _wait_trained(state: Any) -> None:
    trainer = state.trainer
    target = trainer.frames_submitted - trainer.frames_dropped
    deadline = time.monotonic() + WAIT_S
    while trainer.status()["frames_trained"] < target and time.monotonic() < deadline and trainer.alive():
        time.sleep(0.01)  # status() reads progress and leaves the published weights to the pipeline


def run_pipeline(name: str, frames: list[Frame], options: dict[str, Any], sync: bool) -> tuple[list, dict]:
    """Outputs of one pipeline over the frames, and (for online runs) the training record."""
    pipeline = pipelines.get(name, **options)
    state = pipeline.start(frames[0].height, frames[0].width)
    outs = []
    try:
        for frame in frames:
            out, state = pipeline.step(frame, state)
            outs.append(out["color"])
            if sync and getattr(state, "trainer", None) is not None:
                _wait_trained(state)
        record = {}
        if getattr(state, "trainer", None) is not None:
            record = {"status": state.online_status, "loss_per_frame": state.trainer.losses}
    finally:
        state.close()
    return outs, record


def load_sequence(spec: str) -> tuple[str, list[Frame], list[np.ndarray]]:
    """A folder of EXR frames, or `synthetic:HxWxN` (bench.synthetic, seed 999)."""
    if spec.startswith("synthetic:"):
        from bench.synthetic import synthetic_sequence

        height, width, count = (int(v) for v in spec.split(":")[1].split("x"))
        layers = synthetic_sequence(height, width, count, spp=8, seed=999)
        frames = [Frame.from_buffers(x) for x in layers]
    else:
        frames = [read_frame(p) for p in list_sequence(spec)]
    return Path(spec).name, frames, [f["reference"] for f in frames]


def quality(args: argparse.Namespace) -> dict[str, Any]:
    online = {"online": True, "publish_every": 1, "crop": args.crop, "seed": args.seed}
    variants: dict[str, Any] = {
        "noisy": lambda frames: ([f["color"] for f in frames], {}),
        "crossregression (pilots alone)": lambda frames: ([_pilots_alone(f) for f in frames], {}),
        "crossreg warm start, no online": lambda frames: run_pipeline("crossreg", frames, {}, args.sync),
        "crossreg online from random init": lambda frames: run_pipeline(
            "crossreg", frames, {**online, "random_init": True}, args.sync),
        "crossreg warm start + online": lambda frames: run_pipeline("crossreg", frames, online, args.sync),
        "OIDN high": lambda frames: ([_oidn(f) for f in frames], {}),
    }  # fmt: skip
    if "bmfr" in pipelines.names():
        variants["bmfr"] = lambda frames: run_pipeline("bmfr", frames, {}, False)
    report: dict[str, Any] = {"sequences": {}, "mode": "sync" if args.sync else "async", "crop": args.crop}
    for spec in args.sequence:
        name, frames, refs = load_sequence(spec)
        rows = {}
        for label, run in variants.items():
            start = time.perf_counter()
            outs, record = run(frames)
            errors = [rel_l2(o, r) for o, r in zip(outs, refs, strict=True)]
            dssims = [dssim(o, r) for o, r in zip(outs, refs, strict=True)]
            rows[label] = {
                "relL2": float(np.mean(errors)), "1-SSIM": float(np.mean(dssims)),
                "relL2_per_frame": [round(e, 5) for e in errors], "seconds": round(time.perf_counter() - start, 1),
                **({"online": record} if record else {}),
            }  # fmt: skip
            log.info("%-28s %-36s relL2 %.4f  1-SSIM %.4f", name, label, rows[label]["relL2"], rows[label]["1-SSIM"])
        size = f"{frames[0].width}x{frames[0].height}"
        report["sequences"][name] = {"size": size, "frames": len(frames), "methods": rows}
    return report


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - start))
    return float(statistics.median(times))


def _interleaved_ms(first, second, repeats: int) -> tuple[float, float]:
    """Medians of `first` and `second` timed alternately (A B A B ...), so a shared CPU's load drifts hit
    both alike."""
    a, b = [], []
    for _ in range(repeats):
        for fn, times in ((first, a), (second, b)):
            start = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - start))
    return float(statistics.median(a)), float(statistics.median(b))


def _time_size(width: int, height: int, repeats: int) -> dict[str, float]:
    import torch  # noqa: F401  (the training step below)

    from bench.synthetic import synthetic_sequence
    from models.nets.crossreg_unet import make_unet
    from models.train.step import make_optimizer, samples_to_tensor, train_step
    from service.online.trainer import random_crop
    from service.pipelines.crossreg import filter_frame

    layers = synthetic_sequence(height, width, 2, spp=4, seed=1)
    frames = [Frame.from_buffers(x) for x in layers]
    pipeline = pipelines.get("crossreg")
    state = pipeline.start(height, width)
    _, state = pipeline.step(frames[0], state)  # warm: history exists, kernels compiled
    history = state.history

    def step() -> None:
        state.history = history
        pipeline.step(frames[1], state)

    options = pipeline.options  # the served settings: the averaged pilots, the filter's floors
    prepared = prepare_frame(frames[1], history, average=options.average_halves)
    params = state.model.run_planes(prepared.planes)
    floors = (options.min_alpha, options.pilot_bandwidth)  # the served filter's; training takes min_alpha alone
    sample = prepared.sample()
    net = make_unet(seed=0)
    opt = make_optimizer(net)
    rng = np.random.default_rng(0)
    crop128 = samples_to_tensor(random_crop(sample, 128, 4, rng))
    crossreg_ms, oidn_ms = _interleaved_ms(step, lambda: _oidn(frames[1]), repeats)
    row = {
        "crossreg inference (whole step)": crossreg_ms,
        "OIDN high (pyoidn, albedo + normal)": oidn_ms,
        "  cross-regression + reprojection + screening": _median_ms(
            lambda: prepare_frame(frames[1], history, average=options.average_halves), repeats),
        "  U-Net (ONNX Runtime)": _median_ms(lambda: state.model.run_planes(prepared.planes), repeats),
        "  spatiotemporal filter (numba)": _median_ms(lambda: filter_frame(prepared, params, *floors), repeats),
        "training step, 128x128 crop (torch, 1 thread)": _median_ms(lambda: train_step(net, opt, crop128, floors[0]),
                                                                    repeats),
    }
    if width * height <= 256 * 256:
        whole = samples_to_tensor(random_crop(sample, 0, 4, rng))
        row["training step, whole frame (torch, 1 thread)"] = _median_ms(lambda: train_step(net, opt, whole, floors[0]),
                                                                         repeats)
    return {k: round(v, 1) for k, v in row.items()}


def timing(args: argparse.Namespace) -> dict[str, Any]:
    """Median ms per frame: crossreg inference (steady state), its stages, one training step, OIDN high."""
    import torch

    torch.set_num_threads(1)
    out: dict[str, Any] = {}
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        out[size] = _time_size(width, height, args.repeats)
        for k, v in out[size].items():
            log.info("%10s %-48s %9.1f ms", size, k, v)
    return out


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    parser = argparse.ArgumentParser(
        prog="python -m models.train.crossreg_evidence", description=__doc__.splitlines()[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    q = sub.add_parser("quality")
    q.add_argument("--sequence", action="append", default=[], help="EXR folder or synthetic:HxWxN (repeatable)")
    q.add_argument("--crop", type=int, default=0, help="online training crop (0: whole frame)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--async", dest="sync", action="store_false", help="real time: do not wait for the worker")
    t = sub.add_parser("timing")
    t.add_argument("--sizes", nargs="+", default=["256x256", "1280x720"], help="WxH")
    t.add_argument("--repeats", type=int, default=3)
    for p in (q, t):
        p.add_argument("--out", type=Path, default=None, help="write the JSON report here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = quality(args) if args.command == "quality" else timing(args)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
