"""Frame: the named float32 buffers one renderer frame consists of (see shared FRAME_FORMAT.md).

Every interface (EXR files, REST, streaming, CLI) builds a `Frame` through `Frame.from_buffers`,
the one place where the buffer contract is checked: channel counts, equal sizes, dtype, and the
repair of NaN/Inf values. Code past that point trusts its inputs.

In memory each buffer is a C-contiguous float32 array of shape (H, W, C).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LayerSpec:
    """One layer of the frame format."""

    name: str
    channels: tuple[str, ...]  # channel names in memory order, e.g. ("R", "G", "B")
    meaning: str  # one line, with units
    # Value that replaces NaN/Inf; None means "the largest finite value of the layer" (used for
    # depth, whose convention for 'nothing hit' is a large finite distance).
    fill: float | None = 0.0
    # Largest magnitude a finite value may have; beyond it the frame is refused naming the layer (None: any).
    limit: float | None = None


# Radiance beyond this is refused: 20 orders of magnitude above a sunlit scene (~1e9 W/m^2/sr), and the
# stages' float32 sums and squares of it stay finite (bench.stability's radiance_1e20 case passes).
RADIANCE_LIMIT = 1e30
# Albedo in [0, 1] and unit normals, with room for renderers' overshoot; far beyond it products overflow.
GUIDE_LIMIT = 1e6


_RGB = ("R", "G", "B")
LAYERS: dict[str, LayerSpec] = {
    spec.name: spec
    for spec in (
        LayerSpec("color", _RGB, "noisy HDR radiance, linear, mean of all samples", limit=RADIANCE_LIMIT),
        LayerSpec("colorA", _RGB, "radiance from the first half of the samples", limit=RADIANCE_LIMIT),
        LayerSpec("colorB", _RGB, "radiance from the second, disjoint half of the samples", limit=RADIANCE_LIMIT),
        LayerSpec("albedo", _RGB, "albedo of the first visible surface, [0, 1]", limit=GUIDE_LIMIT),
        LayerSpec("normal", ("X", "Y", "Z"), "world-space unit shading normal, zero where nothing hit",
                  limit=GUIDE_LIMIT),
        LayerSpec("depth", ("Z",), "camera distance to the first visible surface, scene units", None),
        LayerSpec("motion", ("X", "Y"), "backward motion in pixels to the previous frame"),
        LayerSpec("motionDual", ("X", "Y"), "dual motion vectors in pixels (Zeng et al.)"),
        LayerSpec("roughness", ("Y",), "surface roughness of the first visible surface, [0, 1]"),
        LayerSpec("ao", ("Y",), "ambient occlusion of the first visible surface, [0, 1]"),
        LayerSpec("sampleCount", ("Y",), "number of samples n in the pixel"),
        LayerSpec("bcMean", _RGB, "mean of the Box-Cox (lambda 1/2) transformed samples"),
        LayerSpec("bcM2", _RGB, "central second moment of the transformed samples (sum / n)"),
        LayerSpec("bcM3", _RGB, "central third moment of the transformed samples (sum / n)"),
        LayerSpec("emission", _RGB, "noise-free directly visible emitted radiance, linear", limit=RADIANCE_LIMIT),
        LayerSpec("error", ("Y",), "output only: estimated relative squared error, per tile and interpolated, of "
                  "the denoisers auto chose run on half the samples (a scale for adaptive sampling)"),
        LayerSpec("reference", _RGB, "converged radiance of the same frame (evaluation only)", limit=RADIANCE_LIMIT),
    )
}

# Layers holding radiance: the ones the emission split and the repair-as-zero-radiance rule apply to.
RADIANCE_LAYERS = ("color", "colorA", "colorB")


class FrameError(ValueError):
    """A frame that breaks the buffer contract; `layer` names the offending layer when there is one."""

    def __init__(self, message: str, layer: str | None = None):
        super().__init__(message)
        self.layer = layer


@dataclass
class Frame:
    """Named buffers of one frame, all float32 (H, W, C) with the same H and W.

    `nonfinite` counts, per layer, the NaN/Inf values that were replaced when the frame was built
    (NaN/Inf radiance becomes zero radiance, a NaN normal the zero normal, NaN depth the largest
    finite depth of the frame). A denoiser never sees them.
    """

    buffers: dict[str, np.ndarray]
    nonfinite: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_buffers(cls, buffers: Mapping[str, np.ndarray], *, repair: bool = True) -> Frame:
        """Validate and convert `buffers` into a Frame.

        buffers: layer name -> array of shape (H, W, C) or (H, W) for one-channel layers, any real
            dtype (converted to float32). Unknown layer names are ignored. When `color` is absent
            but `colorA` and `colorB` are present, `color` is their mean.
        Raises FrameError naming the layer on a wrong channel count, a size that differs from the
        other layers, an empty frame, no known layer at all, or a finite value beyond the layer's
        `limit` (radiance beyond RADIANCE_LIMIT, albedo or normal beyond GUIDE_LIMIT).
        """
        known = {name: arr for name, arr in buffers.items() if name in LAYERS}
        if not known:
            raise FrameError(f"frame has no known layer (got {sorted(buffers)}); expected some of {list(LAYERS)}")
        size: tuple[int, int] | None = None
        size_from = ""
        out: dict[str, np.ndarray] = {}
        for name, value in known.items():
            arr = _as_hwc(name, value)
            if size is None:
                size, size_from = arr.shape[:2], name
                if size[0] < 1 or size[1] < 1:
                    raise FrameError(f"layer '{name}' is empty: size {size[1]}x{size[0]}", name)
            elif arr.shape[:2] != size:
                raise FrameError(
                    f"layer '{name}' is {arr.shape[1]}x{arr.shape[0]} but layer '{size_from}' is "
                    f"{size[1]}x{size[0]} (width x height); all layers must have one size",
                    name,
                )
            out[name] = arr
        counts: dict[str, int] = {}
        if repair:
            for name in out:
                out[name], bad = _repair(name, out[name])
                if bad:
                    counts[name] = bad
        if "color" not in out and "colorA" in out and "colorB" in out:
            out["color"] = 0.5 * (out["colorA"] + out["colorB"])
        return cls(out, counts)

    @property
    def height(self) -> int:
        return next(iter(self.buffers.values())).shape[0]

    @property
    def width(self) -> int:
        return next(iter(self.buffers.values())).shape[1]

    @property
    def nonfinite_total(self) -> int:
        return sum(self.nonfinite.values())

    def __contains__(self, name: object) -> bool:
        return name in self.buffers

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.buffers[name]
        except KeyError:
            raise FrameError(f"frame has no layer '{name}'", name) from None

    def get(self, name: str) -> np.ndarray | None:
        return self.buffers.get(name)

    def require(self, layers: Iterable[str], *, who: str = "this pipeline") -> None:
        """Raise FrameError naming the first of `layers` the frame lacks."""
        for name in layers:
            if name not in self.buffers:
                have = ", ".join(sorted(self.buffers))
                raise FrameError(f"missing layer '{name}' required by {who} (frame has: {have})", name)

    def replace(self, **buffers: np.ndarray) -> Frame:
        """A copy with some buffers replaced or added (trusted: no validation), same repair counts."""
        return Frame({**self.buffers, **buffers}, dict(self.nonfinite))


def _as_hwc(name: str, value: np.ndarray) -> np.ndarray:
    """Layer `name` as a C-contiguous float32 (H, W, C) array with the spec's channel count."""
    spec = LAYERS[name]
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiub":
        raise FrameError(f"layer '{name}' has dtype {arr.dtype}; expected a real number type", name)
    if arr.ndim == 2 and len(spec.channels) == 1:
        arr = arr[:, :, None]
    expected = len(spec.channels)
    if arr.ndim != 3 or arr.shape[2] != expected:
        raise FrameError(
            f"layer '{name}' has shape {arr.shape}; expected (H, W, {expected}) "
            f"with channels {' '.join(spec.channels)}",
            name,
        )
    with np.errstate(over="ignore", invalid="ignore"):
        return np.ascontiguousarray(arr, dtype=np.float32)


def _repair(name: str, arr: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace NaN/Inf in layer `name`; returns the repaired array and how many values were replaced.
    Raises FrameError when a finite value exceeds the layer's `limit` in magnitude."""
    limit = LAYERS[name].limit
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(arr) if limit is None else ~(np.abs(arr) <= np.float32(limit))  # NaN fails <=
    count = int(bad.sum())
    if not count:
        return arr, 0
    if limit is not None:
        outside = arr[bad]
        outside = np.abs(outside[np.isfinite(outside)])
        if outside.size:
            raise FrameError(f"layer '{name}' has values up to {outside.max():.3g} in magnitude; at most "
                             f"{limit:.3g} is accepted (NaN/Inf are repaired, finite values this large are refused)",
                             name)
    fill = LAYERS[name].fill
    if fill is None:
        finite = arr[~bad]
        fill = float(finite.max()) if finite.size else 0.0
    arr = arr.copy()
    arr[bad] = fill
    return arr, count


def from_two_renders(first: Frame, second: Frame) -> Frame:
    """`first` with the halves of a split made from two renders of the same frame with different seeds:
    `colorA` its `color`, `colorB` the `color` of `second`, `color` their mean. The renders must be
    independent (for Cycles: both skip sample 0, which sits at the pixel centre whatever the seed).
    FrameError when the sizes differ (naming `colorB`) or either lacks `color`. Both are repaired Frames: their
    repair counts move with their colours."""
    rest = {k: v for k, v in first.buffers.items() if k != "color"}
    joined = Frame.from_buffers({**rest, "colorA": first["color"], "colorB": second["color"]}, repair=False)
    counts = {k: v for k, v in first.nonfinite.items() if k != "color"}
    counts.update({half: frame.nonfinite["color"] for half, frame in (("colorA", first), ("colorB", second))
                   if "color" in frame.nonfinite})
    return Frame(joined.buffers, counts)


# Layers only a denoiser writes (never read from an input), and what a denoised frame carries to a file or an
# HTTP answer: the result and those of them the pipeline makes
DIAGNOSTICS = ("error",)
OUTPUT_LAYERS = ("color", *DIAGNOSTICS)
