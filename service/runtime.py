"""ONNX Runtime sessions for the networks of the pipelines: thread settings, the model's own contract read
from its metadata, and weight hot-swap.

Every exported network carries a JSON metadata entry `mcdenoise` (written by export/): its input and
output channel groups (service.layout.ChannelGroup, with transforms), its alignment, and the name and
shape of every weight initializer. `OnnxModel` reads it, pads inputs to the alignment and crops outputs,
so no pipeline hard-codes any of it.

Hot-swap: `OnnxModel.swap_weights` builds a new session from the same graph bytes with the new weights
given as `SessionOptions.add_initializer` overrides (OrtValues on numpy arrays; no re-export, no graph
edit), then replaces the live session in one assignment. Weights that are not finite, or whose names or
shapes do not match the graph, are refused (WeightError) and the current session stays. For the 30K
parameter crossreg U-Net the rebuild takes a few milliseconds (see docs/crossreg.md).

Recurrent state: a network whose metadata lists `state` (ModelInfo.state) takes each hidden state as an
explicit input and returns its next value as an output (shared ARCHITECTURE.md); the pipeline keeps it
between frames and calls `OnnxModel.run` with all inputs by name.

Optimisation: swappable models (the default) run at ORT_ENABLE_EXTENDED (see `session_options`); a model
built with `swappable=False` runs at ORT_ENABLE_ALL (NCHWc convolutions, faster) and refuses
`swap_weights`.

Threads: `threads` argument, else the environment variable MCDENOISE_ORT_THREADS, else ONNX Runtime's
default (one per physical core).
"""

from __future__ import annotations

import functools
import json
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from service.layout import ChannelGroup, groups_from_json, pad_planes, total_channels

METADATA_KEY = "mcdenoise"  # ONNX metadata_props key of the JSON contract
THREADS_ENV = "MCDENOISE_ORT_THREADS"  # intra-op threads when no argument says otherwise (0: ORT default)
SHIPPED_WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "weights"  # package data (models/weights)
WEIGHTS_DIR_ENV = "MCDENOISE_WEIGHTS_DIR"  # an operator's folder of more .onnx files (optional)


class WeightError(ValueError):
    """New weights that do not fit the graph (names, shapes, dtype)."""


class NonFiniteWeightsError(WeightError):
    """New weights with NaN or Inf values."""


def weight_files() -> dict[str, Path]:
    """The weight registry: name (file stem) -> .onnx file, from the shipped models/weights/*.onnx and, when
    $MCDENOISE_WEIGHTS_DIR names a folder, its *.onnx (a name there replaces a shipped one). Pipelines take
    a name from here, never a path, so a client cannot make the server open any other file."""
    folders = [SHIPPED_WEIGHTS]
    extra = os.environ.get(WEIGHTS_DIR_ENV, "").strip()
    if extra:
        folders.append(Path(extra))
    return {p.stem: p for folder in folders if folder.is_dir() for p in sorted(folder.glob("*.onnx")) if p.is_file()}


def weight_names(network: str | None = None) -> tuple[str, ...]:
    """The names of `weight_files`, sorted: the choices of a pipeline's `weights` option. With `network`,
    only the files whose metadata names that network, and the files that are not readable models (so that
    choosing one says so, see service/pipelines/networks.py)."""
    files = weight_files()
    return tuple(sorted(name for name, path in files.items() if network is None or
                        weight_network(path) in (network, None)))


def weight_network(path: Path) -> str | None:
    """The `network` named in a weights file's metadata; None when it is not a model with our metadata.
    Cached per (path, modification time, size)."""
    stat = path.stat()
    return _network_of(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=256)
def _network_of(path: str, _mtime_ns: int, _size: int) -> str | None:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    options.log_severity_level = 4  # fatal only: a file that is not a model is an answer here, not an error
    try:
        text = _contract(_session(Path(path).read_bytes(), options))
        return str(json.loads(text)["network"]) if text else None
    except Exception:  # ONNX Runtime raises its own types for a file that is not a model
        return None


def session_options(threads: int | None = None, *, optimize_all: bool = False) -> ort.SessionOptions:
    """SessionOptions with `threads` intra-op threads (None: $MCDENOISE_ORT_THREADS, else ORT default);
    `optimize_all`: ORT_ENABLE_ALL instead of EXTENDED (only for models whose weights are never swapped)."""
    if threads is None:
        raw = os.environ.get(THREADS_ENV, "0")
        try:
            threads = int(raw)
        except ValueError:
            raise ValueError(f"{THREADS_ENV} must be an integer, got {raw!r}") from None
    if threads < 0:
        raise ValueError(f"thread count must be >= 0, got {threads}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    # Not ORT_ENABLE_ALL: in onnxruntime 1.31 its NCHWc layout optimizer bakes the file's initializers into
    # the optimized graph and silently ignores add_initializer overrides (the hot-swap would do nothing;
    # tests/service/online/test_runtime.py catches it). EXTENDED keeps the Conv+ReLU fusions.
    level = ort.GraphOptimizationLevel
    options.graph_optimization_level = level.ORT_ENABLE_ALL if optimize_all else level.ORT_ENABLE_EXTENDED
    options.log_severity_level = 3  # errors only
    return options


@dataclass(frozen=True)
class StateSpec:
    """One recurrent state tensor: fed as input `input`, its next value returned as output `output`."""

    input: str
    output: str
    channels: int
    scale: int  # the state's height and width are the padded frame's divided by this

    def shape(self, height: int, width: int) -> tuple[int, int, int, int]:
        """(1, channels, rows, columns) for a padded frame of height x width pixels."""
        return (1, self.channels, height // self.scale, width // self.scale)


@dataclass(frozen=True)
class ModelInfo:
    """The contract an exported network carries in its metadata."""

    network: str  # e.g. "crossreg_unet"
    alignment: int  # height and width must be multiples of it (the runtime pads)
    input_name: str
    input_groups: tuple[ChannelGroup, ...]  # channel order of the input, with transforms
    output_name: str
    output_groups: tuple[ChannelGroup, ...]
    weight_shapes: dict[str, tuple[int, ...]]  # initializer name -> shape: what a hot-swap may replace
    metadata: dict[str, Any]  # everything, as stored
    state: tuple[StateSpec, ...] = ()  # recurrent state, in the graph's input order

    @classmethod
    def from_json(cls, text: str) -> ModelInfo:
        meta = json.loads(text)
        ((input_name, inputs),) = meta["inputs"].items()
        ((output_name, outputs),) = meta["outputs"].items()
        return cls(
            network=str(meta["network"]),
            alignment=int(meta["alignment"]),
            input_name=input_name,
            input_groups=groups_from_json(inputs),
            output_name=output_name,
            output_groups=groups_from_json(outputs),
            weight_shapes={k: tuple(v) for k, v in meta["weights"].items()},
            metadata=meta,
            state=tuple(StateSpec(str(x["input"]), str(x["output"]), int(x["channels"]), int(x["scale"]))
                        for x in meta.get("state", ())),
        )


def _session(model_bytes: bytes, options: ort.SessionOptions) -> ort.InferenceSession:
    return ort.InferenceSession(model_bytes, sess_options=options, providers=["CPUExecutionProvider"])


def _contract(session: ort.InferenceSession) -> str | None:
    """The JSON text of a model's METADATA_KEY entry; None when it has none."""
    return session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)


class OnnxModel:
    """One ONNX network with its metadata contract and swappable weights.

    `version` counts swaps (0: the weights stored in the file). Thread-safe for one caller running while
    another swaps: `run_*` uses whichever session was live when it started.
    """

    def __init__(self, model_bytes: bytes, *, threads: int | None = None, swappable: bool = True):
        self._bytes = model_bytes
        self._threads = threads
        self.swappable = swappable
        self._session_obj = _session(model_bytes, session_options(threads, optimize_all=not swappable))
        text = _contract(self._session_obj)
        if text is None:
            raise ValueError(f"ONNX model has no '{METADATA_KEY}' metadata; export it with export/")
        self.info = ModelInfo.from_json(text)
        self.version = 0
        self._overrides: dict[str, np.ndarray] = {}  # weights swapped in so far, name -> float32 array
        self._keep_alive: list[ort.OrtValue] = []  # OrtValues the live session's overrides point into
        self._lock = threading.Lock()

    @classmethod
    def from_file(cls, path: str | Path, *, threads: int | None = None, swappable: bool = True) -> OnnxModel:
        return cls(Path(path).read_bytes(), threads=threads, swappable=swappable)

    def copy(self) -> OnnxModel:
        """An independent model (own session, own weights version) on the same graph bytes."""
        return OnnxModel(self._bytes, threads=self._threads, swappable=self.swappable)

    @property
    def model_bytes(self) -> bytes:
        return self._bytes

    def run(self, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Every input by name (NCHW float32, height and width multiples of the alignment) -> every output
        by name."""
        session = self._session_obj
        names = [o.name for o in session.get_outputs()]
        return dict(zip(names, session.run(names, dict(feeds)), strict=True))

    def run_nchw(self, x: np.ndarray) -> np.ndarray:
        """x: (N, C_in, H, W) float32, H and W multiples of the alignment -> (N, C_out, H, W) float32."""
        return self._session_obj.run(None, {self.info.input_name: x})[0]

    def run_planes(self, planes: np.ndarray) -> np.ndarray:
        """planes: (C_in, H, W) float32 in info.input_groups order, any H and W (padded here by edge
        replication to the alignment, cropped back) -> (C_out, H, W) float32 in info.output_groups order,
        contiguous. No copy of the input or the output when H and W are multiples of the alignment."""
        expected = total_channels(self.info.input_groups)
        if planes.ndim != 3 or planes.shape[0] != expected:
            raise ValueError(f"network input has shape {planes.shape}; expected ({expected}, H, W)")
        height, width = planes.shape[1:]
        padded = np.ascontiguousarray(pad_planes(planes, self.info.alignment), dtype=np.float32)
        out = self.run_nchw(padded[None])[0]
        return np.ascontiguousarray(out[:, :height, :width])

    def check_weights(self, weights: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Validated float32 copies of `weights`; raises WeightError / NonFiniteWeightsError naming the first
        offender. Every name must be a weight of the graph with its shape; a subset is allowed."""
        if not weights:
            raise WeightError("no weights given")
        checked: dict[str, np.ndarray] = {}
        for name, value in weights.items():
            shape = self.info.weight_shapes.get(name)
            if shape is None:
                raise WeightError(f"'{name}' is not a weight of network '{self.info.network}'")
            arr = np.asarray(value)
            if arr.shape != shape:
                raise WeightError(f"weight '{name}' has shape {arr.shape}; the graph needs {shape}")
            if arr.dtype.kind != "f":
                raise WeightError(f"weight '{name}' has dtype {arr.dtype}; expected float")
            arr = np.ascontiguousarray(arr, dtype=np.float32)
            bad = int((~np.isfinite(arr)).sum())
            if bad:
                raise NonFiniteWeightsError(f"weight '{name}' has {bad} non-finite values; weights refused")
            checked[name] = arr
        return checked

    def swap_weights(self, weights: Mapping[str, np.ndarray]) -> int:
        """Replace (some of) the weights; returns the new version. Weights not named keep their current
        values. On any error the live session and weights stay."""
        if not self.swappable:
            raise WeightError(f"network '{self.info.network}' was loaded without weight swapping")
        checked = self.check_weights(weights)
        with self._lock:
            overrides = {**self._overrides, **checked}
            options = session_options(self._threads)
            values = [ort.OrtValue.ortvalue_from_numpy(arr) for arr in overrides.values()]
            for name, value in zip(overrides, values, strict=True):
                options.add_initializer(name, value)
            session = _session(self._bytes, options)
            self._session_obj, self._keep_alive, self._overrides = session, values, overrides
            self.version += 1
            return self.version


def default_init(weight_shapes: Mapping[str, tuple[int, ...]], seed: int = 0) -> dict[str, np.ndarray]:
    """Random weights as PyTorch initialises Conv layers by default (kaiming-uniform with a = sqrt(5), i.e.
    U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and for biases alike), in numpy, so a serving session
    can start from random weights (Choi 2024 sec. 4.4) without torch. Biases named `X.bias` take the fan-in
    of `X.weight`. Returns name -> float32 array for every name in `weight_shapes`."""
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for name, shape in weight_shapes.items():
        source = weight_shapes.get(name[: -len("bias")] + "weight", shape) if name.endswith(".bias") else shape
        fan_in = int(np.prod(source[1:])) if len(source) > 1 else int(source[0])
        bound = 1.0 / np.sqrt(max(fan_in, 1))
        out[name] = rng.uniform(-bound, bound, size=shape).astype(np.float32)
    return out
