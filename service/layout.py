"""The one source of truth for how arrays meet networks: channel order, padding alignment, layout.

numpy stages work in (H, W, C); networks in (N, C, H, W), fed and read as channel planes (C, H, W), the
layout the crossreg pipeline keeps between its stages. Every network
input is a stack of named channel groups in a fixed order, each with the transform applied before
stacking. `models/` (training), `export/` (ONNX export, which writes this contract into the file's
metadata) and `service/` (inference, which reads it back) all import these names; nothing else
hard-codes an order or an alignment.

Pure numpy: no torch here (service/ must import without it). Torch callers take
`torch.from_numpy(pad_planes(...)[None])`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

# Transforms a channel group may go through before it enters a network.
TRANSFORM_NONE = "none"
TRANSFORM_LOG1P = "log1p"  # log(1 + x) of linear HDR radiance (Bako et al. 2017; Choi 2024 sec. 4.4)
# log(1 + max(x, 0) / (albedo + ALBEDO_EPS)): albedo-demodulated radiance (Chaitanya 2017 sec. 3.2), log1p-compressed
TRANSFORM_LOG1P_DEMODULATED = "log1p_demodulated"
# log(1 + min(depth / median depth of the frame's hits, 16)): scale-free depth (service/stages/rae_inputs.py)
TRANSFORM_LOG1P_RELATIVE_DEPTH = "log1p_relative_depth"


@dataclass(frozen=True)
class ChannelGroup:
    """A named group of consecutive channels in a network tensor."""

    name: str  # e.g. "pilotA"
    channels: int  # number of channels
    transform: str  # TRANSFORM_*: what was applied to the quantity before stacking
    meaning: str  # one line, with units


# Choi et al. 2024, sec. 4.2 / Fig. 3, in the order of the authors' code (CGLab-GIST/cross-denoiser:
# color1, color2, prev, albedo, normal). The pilots and the previous output arrive in log1p space already
# (the cross-regression stage works there), so `transform` records the space, not a step to repeat.
CROSSREG_INPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("pilotA", 3, TRANSFORM_LOG1P, "cross-regression pilot estimate A, log1p radiance"),
    ChannelGroup("pilotB", 3, TRANSFORM_LOG1P, "cross-regression pilot estimate B, log1p radiance"),
    ChannelGroup("previous", 3, TRANSFORM_LOG1P, "previous output reprojected to this frame, log1p radiance"),
    ChannelGroup("albedo", 3, TRANSFORM_NONE, "albedo of the first visible surface, [0, 1]"),
    ChannelGroup("normal", 3, TRANSFORM_NONE, "world-space unit shading normal, [-1, 1]"),
)

# The six per-pixel filter parameters theta (Choi 2024 sec. 4.2) as the network emits them after its head:
# the five bandwidths as precisions 1 / (theta^2 + eps) (eq. 9 denominators, positive by construction) and
# the temporal blending weight sigmoid(theta_alpha) in (0, 1) (eq. 8).
CROSSREG_OUTPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("precisionA", 1, TRANSFORM_NONE, "1 / (theta_A^2 + eps), per (log1p radiance)^2"),
    ChannelGroup("precisionB", 1, TRANSFORM_NONE, "1 / (theta_B^2 + eps), per (log1p radiance)^2"),
    ChannelGroup("precisionAlbedo", 1, TRANSFORM_NONE, "1 / (theta_albedo^2 + eps), per albedo^2"),
    ChannelGroup("precisionNormal", 1, TRANSFORM_NONE, "1 / (theta_normal^2 + eps), per normal^2"),
    ChannelGroup("precisionPosition", 1, TRANSFORM_NONE, "1 / (theta_position^2 + eps), per (offset / 5 px)^2"),
    ChannelGroup("alpha", 1, TRANSFORM_NONE, "sigmoid(theta_alpha): weight of the current frame, (0, 1)"),
)

# What the online / offline training step needs beyond the network input (Choi 2024 eqs. 11-13), stacked
# after CROSSREG_INPUTS in one (H, W, 15 + 7) training sample. Where reprojection failed, the previous
# pilots are replaced by the current ones (so the temporal term falls back to the spatial one) and
# `valid` is 0 (the filter ignores the history there).
CROSSREG_TARGETS: tuple[ChannelGroup, ...] = (
    ChannelGroup("valid", 1, TRANSFORM_NONE, "1 where the reprojected history is usable, else 0"),
    ChannelGroup("previousPilotA", 3, TRANSFORM_LOG1P, "previous frame's pilot A reprojected, log1p radiance"),
    ChannelGroup("previousPilotB", 3, TRANSFORM_LOG1P, "previous frame's pilot B reprojected, log1p radiance"),
)
CROSSREG_SAMPLE = CROSSREG_INPUTS + CROSSREG_TARGETS

# The recurrent autoencoder (Chaitanya 2017 sec. 3.2: noisy demodulated colour, normal, depth, roughness).
# The paper's normal is view-space (x, y); frames carry world-space normals, so all three components go in.
RAE_INPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("radiance", 3, TRANSFORM_LOG1P_DEMODULATED, "noisy radiance without emission, demodulated"),
    ChannelGroup("normal", 3, TRANSFORM_NONE, "world-space unit shading normal, [-1, 1], 0 where nothing was hit"),
    ChannelGroup("depth", 1, TRANSFORM_LOG1P_RELATIVE_DEPTH, "camera distance relative to the frame's median"),
    ChannelGroup("roughness", 1, TRANSFORM_NONE, "surface roughness, [0, 1]; -1 when the frame has none"),
)
RAE_OUTPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("radiance", 3, TRANSFORM_LOG1P_DEMODULATED, "denoised radiance without emission, demodulated"),
)

# Fast local neural regression (Salmi et al.): the guide network reads the recurrent autoencoder's inputs
# (RAE_INPUTS) and writes the guides of the regression, which standardises them per frame (any units).
FLNR_GUIDES = 4  # guides, all the regression sees: normal and relative depth as the network transformed them
FLNR_OUTPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("guides", FLNR_GUIDES, TRANSFORM_NONE, "FLR guides: normal, relative depth, plus what was learned"),
)


# The multi-scale kernel-predicting network with dual motion vectors (Zeng et al. 2023, sec. 4, Fig. 4): the
# recurrent autoencoder's planes plus the previous output warped to this frame (its recurrent state, an
# explicit part of the input; the noisy radiance where the warp fails and at a sequence's first frame).
KPN_INPUTS: tuple[ChannelGroup, ...] = RAE_INPUTS + (
    ChannelGroup("previous", 3, TRANSFORM_LOG1P_DEMODULATED, "previous output warped to this frame, demodulated"),
)
KPN_TAPS = 25  # a 5 x 5 per-pixel kernel (Zeng 2023 sec. 4.3, Fig. 6)
# The network's raw predictions; the kernel filter (service/stages/kernel_filter.py) normalises them: a softmax
# over each kernel's 25 taps (weights that sum to 1), a sigmoid of each alpha (a weight in (0, 1)).
# Zeng 2023 Fig. 6, finest scale (51 = two 5x5 kernels + alpha_t), at the frame's resolution
KPN_FINE_OUTPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("kernel", KPN_TAPS, TRANSFORM_NONE, "logits of the spatial 5x5 kernel on the noisy radiance"),
    ChannelGroup("temporal", KPN_TAPS, TRANSFORM_NONE, "logits of the 5x5 kernel on the warped previous output"),
    ChannelGroup("alpha", 1, TRANSFORM_NONE, "logit of alpha_t, the weight of the current frame's filtered radiance"),
)
# Zeng 2023 Fig. 6, each coarser scale (26 = a 5x5 kernel + alpha), at 1/2 and 1/4 of the frame's resolution
KPN_COARSE_OUTPUTS: tuple[ChannelGroup, ...] = (
    ChannelGroup("kernel", KPN_TAPS, TRANSFORM_NONE, "logits of the 5x5 kernel on the downsampled noisy radiance"),
    ChannelGroup("alpha", 1, TRANSFORM_NONE, "logit of this scale's weight against the finer one (eq. 4)"),
)


def total_channels(groups: Sequence[ChannelGroup]) -> int:
    return sum(g.channels for g in groups)


def channel_slices(groups: Sequence[ChannelGroup]) -> dict[str, slice]:
    """name -> slice of the channel axis that group occupies."""
    out: dict[str, slice] = {}
    start = 0
    for group in groups:
        out[group.name] = slice(start, start + group.channels)
        start += group.channels
    return out


def stack_planes(groups: Sequence[ChannelGroup], arrays: Mapping[str, np.ndarray]) -> np.ndarray:
    """Stack the (H, W, c) float32 arrays named by `groups`, in their order, into contiguous planes
    (C, H, W) float32: the network's input without its batch axis.

    Raises ValueError naming a missing group or a wrong channel count.
    """
    parts = []
    for group in groups:
        if group.name not in arrays:
            raise ValueError(f"network input '{group.name}' is missing")
        arr = arrays[group.name]
        if arr.ndim != 3 or arr.shape[2] != group.channels:
            raise ValueError(f"network input '{group.name}' has shape {arr.shape}; expected (H, W, {group.channels})")
        parts.append(arr)
    out = np.empty((total_channels(groups), *parts[0].shape[:2]), np.float32)
    for part, where in zip(parts, channel_slices(groups).values(), strict=True):
        out[where] = part.transpose(2, 0, 1)  # plane copies, no per-pixel interleaving
    return out


def groups_to_json(groups: Sequence[ChannelGroup]) -> list[dict[str, object]]:
    return [{"name": g.name, "channels": g.channels, "transform": g.transform, "meaning": g.meaning} for g in groups]


def groups_from_json(items: Sequence[Mapping[str, object]]) -> tuple[ChannelGroup, ...]:
    return tuple(
        ChannelGroup(str(i["name"]), int(i["channels"]), str(i["transform"]), str(i.get("meaning", "")))  # type: ignore[arg-type]
        for i in items
    )


def pad_amounts(height: int, width: int, alignment: int) -> tuple[int, int]:
    """(rows, columns) to add at the bottom and right so both sizes are multiples of `alignment`."""
    if alignment < 1:
        raise ValueError(f"alignment must be >= 1, got {alignment}")
    return (-height) % alignment, (-width) % alignment


def pad_planes(arr: np.ndarray, alignment: int) -> np.ndarray:
    """Pad planes (C, H, W) at the bottom and right by edge replication up to multiples of `alignment`.

    Returns the input itself when no padding is needed. Undo by slicing `out[:, :H, :W]`.
    """
    rows, cols = pad_amounts(arr.shape[1], arr.shape[2], alignment)
    if rows == 0 and cols == 0:
        return arr
    return np.pad(arr, ((0, 0), (0, rows), (0, cols)), mode="edge")
