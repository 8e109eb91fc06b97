"""Renderer dialects: which channels of an EXR file make which layer of the frame format, and how.

Renderers name their buffers their own way and with their own conventions (shared FRAME_FORMAT.md). A
`ChannelMap` says, per frame-format layer, which file channels form it, in the layer's channel order, and
the conversions on the way in: a factor per channel (a flipped axis), a clip range, and channels added to
it. `detect` picks one for a file from its channel names:

- **mcdenoise**: the frame format's own `LAYER.CHANNEL` names, with the leniencies real files need: bare
  `R G B` as `color` when no `color.*` channel exists, the RGB names for XYZ channels (`normal.R` =
  `normal.X`), any single name for a one-channel layer. An alpha channel `A` is never data.
- **blender**: Blender's multilayer EXR (Cycles, EEVEE), channels `VIEWLAYER.PASS.CHANNEL` under any view
  layer name. Its conventions, found on files Blender wrote (models/data/samples/blender, the tests in
  tests/service/test_dialects.py hold them):
  - `color`: `Noisy Image` when present (Blender's denoiser was on and `Combined` is its result), else
    `Combined`.
  - `albedo`: `Denoising Albedo`, clipped to [0, 1]: Cycles adds an emitter's emission to it.
  - `normal`: `Normal`, world space, when present; else `Denoising Normal`, which is in camera space
    (x right, y up, z into the screen). The EXR holds no camera, so it is taken as it is: a filter sees
    the same edges; a temporal pipeline's normal test across frames sees the camera's turn.
  - `depth`: `Denoising Depth` (channel `Z`) when present: the distance along the ray (against `Depth`
    it grows as 1/cos of the angle off the view axis), averaged over the samples, 0 where nothing was hit
    (read as 1e10, a large finite value as the format asks). A silhouette pixel averages its misses as
    0: it reads nearer than its surface (down to ~0.005 on the fixture), which a depth weight treats as an
    edge. Else `Depth`: planar depth, 1e10 for misses, and written by sample 0 alone: a render that
    skips sample 0 (the halves recipe below) has 1e10 in every pixel of it, which the reader notes.
  - `motion`: `Vector` X and -Y. X, Y is the offset to the previous frame in pixels with y up (Z, W: the
    negated offset to the next frame, unused). Warping the previous frame's reference by it lowers the
    error against the current one; any other sign or axis raises it.
  - `emission`: `Emit` (or `Emission`) plus `Env` (or `Environment`) when the file has it: the emitters and the sky
    seen directly, noise-free.
  One view layer is read: the only one, or the one named (`view_layer`); a file with several and no
  name is an error that lists them.
- **mitsuba**: Mitsuba 3's `aov` integrator with an `hdrfilm` (multichannel EXR): the image as bare
  `R G B`; AOVs, named after their type (`aovs="albedo:albedo,sh_normal:sh_normal,depth:depth"`; Mitsuba
  names the channels after the name left of the colon): `albedo.R G B`, `sh_normal.X Y Z` (world space),
  `depth.T` (distance along the ray; 0 where nothing was hit, read as 1e10, a large finite value as the
  format asks). Other AOVs are ignored; a file with `sh_normal.X` or `depth.T` is Mitsuba's.
- **map**: a channel map given by the user (`ChannelMap.from_json`), for any other renderer.

Halves from two renders (`--second-half`, a two-part EXR over HTTP): render the sequence twice with
different seeds. Cycles puts sample 0 of every render at the pixel centre whatever the seed, so two
renders of N samples share it: skip it in both (Sampling > Advanced > Sample Subset: N + 1 samples,
offset 1, length N; `models/data/fixtures/blender_fixture.py`). Measured on the fixture scene at 1 spp
against 4096 spp: the two renders' clipped errors correlate at 0.15 with the seed alone, 0.03 with the
first sample skipped (at 2-8 spp both stay within +-0.07 here). Mitsuba: the sampler's `seed`.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.frame import DIAGNOSTICS, LAYERS, FrameError


class DialectError(FrameError):
    """The file's channels cannot be read as asked: a Blender view layer to choose, or a channel map that
    names channels the file lacks (an error of the frame, not of its encoding)."""


MISS_DEPTH = 1e10  # depth where nothing was hit, when a renderer writes 0 there (Blender's own value)
_ALIASES: dict[int, tuple[tuple[str, ...], ...]] = {  # other channel names accepted per channel count
    3: (("R", "G", "B"), ("X", "Y", "Z")),
    2: (("X", "Y"), ("R", "G"), ("U", "V")),
}


@dataclass(frozen=True)
class LayerSource:
    """How one layer is made from file channels: channels[i] (times scale[i]) is the layer's channel i,
    plus add[i] when given, then clipped to `clip`. `error`: why the file's channels cannot form the layer
    (raised as a FrameError naming it when the layer is read)."""

    channels: tuple[str, ...]
    scale: tuple[float, ...] = ()
    add: tuple[str, ...] = ()
    clip: tuple[float, float] | None = None
    replace_zero: float | None = None  # a value written where every channel is exactly 0 (depth of a miss)
    error: str | None = None

    def file_channels(self) -> tuple[str, ...]:
        return () if self.error else (*self.channels, *self.add)

    def assemble(self, pixels: Mapping[str, np.ndarray], layer: str) -> np.ndarray:
        """The (H, W, C) float32 layer from decoded channels ((H, W) float32 each)."""
        if self.error:
            raise FrameError(self.error, layer)
        out = np.stack([pixels[c] for c in self.channels], axis=-1).astype(np.float32, copy=True)
        if self.scale:
            out *= np.asarray(self.scale, np.float32)
        if self.add:
            out += np.stack([pixels[c] for c in self.add], axis=-1)
        if self.replace_zero is not None:
            out[(out == 0).all(axis=-1)] = self.replace_zero
        if self.clip is not None:  # NaN and infinities stay, for the frame to repair and count
            np.copyto(out, np.clip(out, *self.clip), where=np.isfinite(out))
        return out

    def describe(self) -> str:
        text = " ".join(f"{'-' if s < 0 else ''}{c}" for c, s in zip(self.channels, self.scale or
                                                                         (1.0,) * len(self.channels), strict=True))
        if self.add:
            text += " + " + " ".join(self.add)
        if self.replace_zero is not None:
            text += f", 0 -> {self.replace_zero:g}"
        if self.clip is not None:
            text += f", clipped to [{self.clip[0]:g}, {self.clip[1]:g}]"
        return self.error or text


@dataclass(frozen=True)
class ChannelMap:
    """The layers a file provides and how (`LayerSource`), under the name of its dialect."""

    dialect: str
    layers: Mapping[str, LayerSource] = field(default_factory=dict)
    notes: tuple[str, ...] = ()  # what the reader assumed (a camera-space normal, ...)
    # the channels a denoised result gets beside the input's (`--keep-layers`): a pass of the view layer
    # for Blender, so that its compositor loads it as it loads its own passes
    result: tuple[str, str, str] = ("denoised.R", "denoised.G", "denoised.B")

    @classmethod
    def from_json(cls, source: str | Path | Mapping[str, Any]) -> ChannelMap:
        """A user's channel map: a JSON file (or its parsed object) {"layers": {LAYER: {"channels": [...],
        "scale": [...], "add": [...], "clip": [lo, hi], "replace_zero": v}}}, only "channels" required.
        ValueError naming the layer or key that is wrong."""
        if isinstance(source, Mapping):
            data, where = source, "channel map"
        else:
            where = f"channel map '{source}'"
            try:
                data = json.loads(Path(source).read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
                raise ValueError(f"{where}: {err}") from err
        if not isinstance(data, Mapping) or set(data) - {"layers"} or not isinstance(data.get("layers"), Mapping):
            raise ValueError(f'{where}: expected an object {{"layers": {{LAYER: {{"channels": [...]}}}}}}')
        layers = {name: _parse_source(name, spec, where) for name, spec in data["layers"].items()}
        if not layers:
            raise ValueError(f"{where}: maps no layer")
        return cls("map", layers)

    def missing_channels(self, names: Iterable[str]) -> dict[str, list[str]]:
        """Per layer, the channels it names that are not among `names`."""
        present = set(names)
        out = {layer: [c for c in src.file_channels() if c not in present] for layer, src in self.layers.items()}
        return {layer: cs for layer, cs in out.items() if cs}


def _parse_source(layer: str, spec: Any, where: str) -> LayerSource:
    if layer not in LAYERS:
        raise ValueError(f"{where}: unknown layer '{layer}'; layers: {', '.join(LAYERS)}")
    count = len(LAYERS[layer].channels)
    if not isinstance(spec, Mapping) or set(spec) - {"channels", "scale", "add", "clip", "replace_zero"}:
        raise ValueError(f"{where}: layer '{layer}' takes channels, scale, add, clip and replace_zero")

    def names(key: str) -> tuple[str, ...]:
        value = spec.get(key, [])
        if not (isinstance(value, list) and all(isinstance(v, str) and v for v in value)):
            raise ValueError(f"{where}: layer '{layer}' {key} must be a list of channel names")
        if value and len(value) != count:
            raise ValueError(f"{where}: layer '{layer}' has {count} channel(s); {key} lists {len(value)}")
        return tuple(value)

    channels, add = names("channels"), names("add")
    if not channels:
        raise ValueError(f"{where}: layer '{layer}' needs channels")
    scale = spec.get("scale", [])
    if not (isinstance(scale, list) and len(scale) in (0, count)):
        raise ValueError(f"{where}: layer '{layer}' scale must be {count} finite numbers")
    scale = tuple(_finite(s, f"{where}: layer '{layer}' scale") for s in scale)
    clip = spec.get("clip")
    if clip is not None:
        if not (isinstance(clip, list) and len(clip) == 2):
            raise ValueError(f"{where}: layer '{layer}' clip must be [low, high] with low < high")
        clip = tuple(_finite(v, f"{where}: layer '{layer}' clip") for v in clip)
        if not clip[0] < clip[1]:
            raise ValueError(f"{where}: layer '{layer}' clip must be [low, high] with low < high")
    zero = spec.get("replace_zero")
    zero = None if zero is None else _finite(zero, f"{where}: layer '{layer}' replace_zero")
    return LayerSource(channels, scale, add, clip, zero)


def _finite(value: Any, what: str) -> float:
    """`value` as a finite float32-representable number; ValueError naming `what` otherwise (booleans,
    strings, numbers beyond float32)."""
    try:
        number = float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None
    except OverflowError:
        number = None
    if number is None or not abs(number) <= float(np.finfo(np.float32).max):
        raise ValueError(f"{what} must be finite numbers within float32, got {str(value)[:32]}")
    return number


# ------------------------------------------------------------------------------------------ mcdenoise


def native(names: Iterable[str]) -> ChannelMap:
    """The frame format's own names (module docstring)."""
    names = list(names)
    by_layer: dict[str, list[str]] = {}
    bare = not any(n.startswith("color.") for n in names)
    for full in names:
        layer, _, chan = full.rpartition(".")
        if not layer and bare and full in ("R", "G", "B"):
            layer = "color"
        if layer in LAYERS and layer not in DIAGNOSTICS and chan != "A":  # our outputs are never read
            by_layer.setdefault(layer, []).append(full)
    layers = {}
    for layer, fulls in by_layer.items():
        expected = LAYERS[layer].channels
        short = {f.rpartition(".")[2]: f for f in fulls}
        order = _match(expected, tuple(short))
        if order is None:
            error = (f"layer '{layer}' has {len(short)} channel(s) ({', '.join(sorted(short))}); "
                     f"expected {len(expected)} ({' '.join(expected)})")
            layers[layer] = LayerSource(tuple(fulls), error=error)
        else:
            layers[layer] = LayerSource(tuple(short[c] for c in order))
    return ChannelMap("mcdenoise", layers)


def _match(expected: tuple[str, ...], present: tuple[str, ...]) -> tuple[str, ...] | None:
    if len(expected) == 1 and len(present) == 1:
        return present
    for names in (expected, *_ALIASES.get(len(expected), ())):
        if set(names) == set(present):
            return names
    return None


# -------------------------------------------------------------------------------------------- blender

_BLENDER_PASSES = frozenset({"Combined", "Noisy Image", "Denoising Albedo", "Denoising Normal", "Denoising Depth",
                             "Depth", "Vector", "Normal", "Emit", "Emission", "Env", "Environment"})


def _blender_passes(names: Iterable[str]) -> dict[str, dict[str, dict[str, str]]]:
    """view layer -> pass -> channel letter -> full name, for channels `VIEWLAYER.PASS.CHANNEL` (a view
    layer name may hold dots; a pass name holds none). A view layer has a `Combined` or `Noisy Image` pass;
    a prefix without one (an AOV whose name holds a dot) is not a view layer."""
    out: dict[str, dict[str, dict[str, str]]] = {}
    for full in names:
        parts = full.rsplit(".", 2)
        if len(parts) == 3 and parts[1] in _BLENDER_PASSES:
            out.setdefault(parts[0], {}).setdefault(parts[1], {})[parts[2]] = full
    return {layer: passes for layer, passes in out.items() if {"Combined", "Noisy Image"} & set(passes)}


def blender(names: Iterable[str], view_layer: str | None = None) -> ChannelMap:
    """Blender's multilayer EXR (module docstring). DialectError when the file has several view layers and
    `view_layer` names none of them."""
    passes_by_layer = _blender_passes(names)
    if view_layer is not None:
        if view_layer not in passes_by_layer:
            raise DialectError(f"no view layer '{view_layer}' in the file; it has {', '.join(sorted(passes_by_layer))}")
        passes = passes_by_layer[view_layer]
    elif len(passes_by_layer) == 1:
        view_layer, passes = next(iter(passes_by_layer.items()))
    else:
        raise DialectError(f"the file has view layers {', '.join(sorted(passes_by_layer))}; name one (view_layer)")

    def take(name: str, letters: str) -> tuple[str, ...] | None:
        chans = passes.get(name, {})
        return tuple(chans[c] for c in letters) if all(c in chans for c in letters) else None

    layers: dict[str, LayerSource] = {}
    notes = [f"view layer '{view_layer}'"]
    color = take("Noisy Image", "RGB") or take("Combined", "RGB")
    if color:
        layers["color"] = LayerSource(color)
    if albedo := take("Denoising Albedo", "RGB"):
        layers["albedo"] = LayerSource(albedo, clip=(0.0, 1.0))
    if normal := take("Normal", "XYZ"):
        layers["normal"] = LayerSource(normal)
    elif normal := take("Denoising Normal", "XYZ"):
        layers["normal"] = LayerSource(normal)
        notes.append("normal: Denoising Normal, camera space (no Normal pass)")
    if depth := take("Denoising Depth", "Z"):
        layers["depth"] = LayerSource(depth, replace_zero=MISS_DEPTH)
    elif depth := take("Depth", "Z"):
        layers["depth"] = LayerSource(depth)
        notes.append("depth: Depth, planar, from sample 0 only (no Denoising Depth pass)")
    if vector := take("Vector", "XY"):
        layers["motion"] = LayerSource(vector, scale=(1.0, -1.0))
    emit = take("Emit", "RGB") or take("Emission", "RGB")
    environment = take("Env", "RGB") or take("Environment", "RGB")
    if emit or environment:
        first, second = (emit, environment) if emit else (environment, None)
        layers["emission"] = LayerSource(first, add=second or ())
    return ChannelMap("blender", layers, tuple(notes), tuple(f"{view_layer}.Denoised.{c}" for c in "RGB"))


# -------------------------------------------------------------------------------------------- mitsuba

_MITSUBA = {"albedo": ("albedo", "RGB"), "normal": ("sh_normal", "XYZ"), "depth": ("depth", "T")}


def is_mitsuba(names: Iterable[str]) -> bool:
    names = set(names)
    return {"R", "G", "B"} <= names and bool({"sh_normal.X", "depth.T"} & names)


def mitsuba(names: Iterable[str]) -> ChannelMap:
    """Mitsuba 3's `aov` integrator output (module docstring)."""
    names = set(names)
    layers = {**native(names).layers, "color": LayerSource(("R", "G", "B"))}  # AOVs named after our layers too
    for layer, (aov, letters) in _MITSUBA.items():
        chans = tuple(f"{aov}.{c}" for c in letters)
        if all(c in names for c in chans):
            layers[layer] = LayerSource(chans, replace_zero=MISS_DEPTH if layer == "depth" else None)
    return ChannelMap("mitsuba", layers)


# ------------------------------------------------------------------------------------------- detection

_FORMAT_NAME = re.compile(r"^(" + "|".join(LAYERS) + r")\.[A-Za-z]+$")


def detect(names: Iterable[str], *, channel_map: ChannelMap | None = None, view_layer: str | None = None) -> ChannelMap:
    """The ChannelMap for a file with channels `names`: the user's map when given, else Blender's when the
    file has a view layer's passes, else Mitsuba's AOV layout, else the frame format's. Channels named in
    the frame format (a `reference` added to a Blender file) are read as such in every dialect, and win
    over the dialect's own for the same layer."""
    names = list(names)
    if channel_map is not None:
        return channel_map
    if _blender_passes(names):
        found = blender(names, view_layer)
        ours = native(n for n in names if _FORMAT_NAME.match(n)).layers
        return ChannelMap(found.dialect, {**found.layers, **ours}, found.notes, found.result)
    if is_mitsuba(names) and not any(n.startswith("color.") for n in names):
        return mitsuba(names)
    return native(names)
