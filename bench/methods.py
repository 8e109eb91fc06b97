"""What the benchmark runs: every registered pipeline plus the anchors, behind the one pipeline interface.

Anchors are `Pipeline` subclasses that are *not* registered (the service never offers them), so they
go through the same `Pipeline.step` as the denoisers: the same layer check, the same emission split
(noise-free emission removed before denoising and added back after; not for `noisy`, the input as it came)
and the same finiteness guard. That keeps the comparison about the denoiser alone.

- `noisy`: the input `color` unchanged; the error every denoiser starts from.
- `oidn-high`, `oidn-fast`: Intel Open Image Denoise 2 (PyPI `pyoidn`), RT filter, HDR, with albedo
  and normal as auxiliary images, at quality "high" and "fast". The frame format's albedo and normal
  are first-hit buffers (anti-aliased, without path-tracing noise), so they go in as clean auxiliary
  images (`clean_aux=True`, OIDN's documented setting for noise-free features). With
  `clean_aux=False` OIDN prefilters them and blurs texture detail: on the `textures` benchmark
  sequence that raised its relL2 from 0.016 to 0.068 (frame 4). Its CPU thread count comes from
  OIDN_NUM_THREADS (bench.environment).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from service import pipelines
from service.cli.sequence_args import parse_options
from service.frame import Frame
from service.pipelines.base import Pipeline, SequenceState, Split
from service.pipelines.options import build as build_options

ANCHORS = ("noisy", "oidn-high", "oidn-fast")
# `--anchors` shorthands.
ANCHOR_GROUPS = {"all": ANCHORS, "oidn": ("oidn-high", "oidn-fast"), "none": ()}


class NoisyAnchor(Pipeline):
    name = "noisy"
    guards = False
    summary = "the noisy input itself (anchor)"
    requires = ("color",)

    def denoise_split(self, frame: Frame, state: SequenceState) -> Split:
        """No emission split: at an emitter's edge the split clips the remainder (service/stages/emission.py),
        and the anchor is the input as it came."""
        buffers, state = self.denoise(frame, state)
        return buffers, set(), state

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        return {"color": frame["color"].copy()}, state


class _OidnAnchor(Pipeline):
    """OIDN RT filter on `color` (HDR, clipped at 0: OIDN takes no negative radiance) with clean albedo
    and normal clipped to the ranges OIDN documents ([0, 1] and [-1, 1])."""

    requires = ("color",)
    optional = ("albedo", "normal", "emission")
    quality: ClassVar[str]
    guards = False  # OIDN as its users call it: no exact-pixel emission, no noise clamp or blend
    # Our albedo and normal are first-hit buffers without render noise. With clean_aux OIDN 2 runs its
    # clean-auxiliary models (at quality high a larger network: about 2.3x the time of the default call at
    # 1280x720 here) and keeps texture detail the default blurs.
    clean_aux: ClassVar[bool] = True

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        import pyoidn

        color = np.maximum(frame["color"], 0.0)
        albedo = frame.get("albedo")
        normal = frame.get("normal")
        if albedo is not None:
            albedo = np.clip(albedo, 0.0, 1.0)
        if normal is not None and albedo is None:  # OIDN accepts a normal only together with an albedo
            normal = None
        if normal is not None:
            normal = np.clip(normal, -1.0, 1.0)
        out = pyoidn.denoise(color, albedo, normal, hdr=True, clean_aux=self.clean_aux, quality=self.quality)
        return {"color": np.asarray(out, np.float32)}, state


class OidnHighAnchor(_OidnAnchor):
    name = "oidn-high"
    summary = "Intel Open Image Denoise 2, quality high, clean albedo + normal (anchor)"
    quality = "high"


class OidnHighDefaultAnchor(_OidnAnchor):
    name = "oidn-high-default"
    summary = "Intel Open Image Denoise 2, quality high, default (noisy-aux) albedo + normal handling (anchor)"
    quality = "high"
    clean_aux = False


class OidnFastAnchor(_OidnAnchor):
    name = "oidn-fast"
    summary = "Intel Open Image Denoise 2, quality fast, clean albedo + normal (anchor)"
    quality = "fast"


_ANCHOR_CLASSES: dict[str, type[Pipeline]] = {
    c.name: c for c in (NoisyAnchor, OidnHighAnchor, OidnHighDefaultAnchor, OidnFastAnchor)
}


@dataclass(frozen=True)
class Method:
    """One column of the benchmark: a registered pipeline or an anchor."""

    name: str
    kind: str  # "pipeline" or "anchor"
    make: Callable[[], Pipeline]  # a new pipeline object (options at their defaults)
    requires: tuple[str, ...]  # layers a frame must have
    temporal: bool  # whether the output depends on earlier frames

    def missing(self, layers: set[str] | frozenset[str]) -> list[str]:
        """Required layers absent from `layers` (a sequence's layers); empty when it can run."""
        return [name for name in self.requires if name not in layers]

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "requires": list(self.requires), "temporal": self.temporal}


def _method(cls: type[Pipeline], kind: str, make: Callable[[], Pipeline]) -> Method:
    return Method(cls.name, kind, make, tuple(cls.requires), bool(cls.temporal))


def pipeline_method(spec: str) -> Method:
    """A registered pipeline as a Method. `spec` is its name, or its name with options,
    `NAME:KEY=VALUE,KEY=VALUE` (values parsed as the CLI's `--option`), which also names the column: e.g.
    `crossreg:online=true`. Raises UnknownPipelineError naming the choices, or OptionError naming a bad
    option, here rather than at the first frame."""
    name, _, text = spec.partition(":")
    cls = pipelines.pipeline_class(name)
    options = parse_options(text.split(",")) if text else {}
    build_options(cls.Options, options, f"pipeline '{name}'")
    return Method(spec, "pipeline", lambda: pipelines.get(name, **options), tuple(cls.requires), bool(cls.temporal))


def anchor_method(name: str) -> Method:
    try:
        cls = _ANCHOR_CLASSES[name]
    except KeyError:
        raise ValueError(f"unknown anchor '{name}'; anchors: {', '.join(ANCHORS)}") from None
    return _method(cls, "anchor", cls)


def select(pipeline_names: list[str] | None, anchor_names: list[str] | None) -> list[Method]:
    """Methods for `--pipelines` and `--anchors` values.

    pipeline_names: registered names, or ["all"] / None for every registered pipeline, [] or ["none"]
    for none. anchor_names: anchor names or the groups in ANCHOR_GROUPS; None means "all". The
    `noisy` anchor is always included when any anchor is: it is the error scale of every table.
    """
    if pipeline_names is None or "all" in pipeline_names:
        chosen = pipelines.names()
    else:
        chosen = [n for n in pipeline_names if n != "none"]
    methods = [pipeline_method(n) for n in dict.fromkeys(chosen)]
    anchors: list[str] = []
    for name in anchor_names if anchor_names is not None else ["all"]:
        anchors.extend(ANCHOR_GROUPS.get(name, (name,)))
    if anchors:
        anchors.insert(0, "noisy")
    return methods + [anchor_method(n) for n in dict.fromkeys(anchors)]
