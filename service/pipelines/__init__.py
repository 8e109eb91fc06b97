"""Registry of denoising pipelines. Every module in this package that defines a `Pipeline` subclass
decorated with `register` is imported here, so adding a denoiser is adding one module."""

from __future__ import annotations

import importlib
import pkgutil
from typing import Any

from service.pipelines.base import Pipeline, SequenceState

__all__ = ["Pipeline", "SequenceState", "register", "get", "names", "describe", "auto", "DEFAULT", "AUTO"]

_REGISTRY: dict[str, type[Pipeline]] = {}

# Used when an API caller names no pipeline: relL2 1.88x OIDN-high's at 108 ms/MP in `make bench` (2026-11-26).
# `auto` has the lower error there (1.68x) but takes about 6x the time per frame; the CLI defaults to it.
DEFAULT = "crossregression"
AUTO = "auto"  # the per-tile blend (service/pipelines/tiled.py); the CLI's default
# Preference of `auto`, best first by the benchmark's relL2 against OIDN-high at moderate cost (`make bench`,
# 2026-11-27: kpn 1.45x at 0.30x OIDN-high's time at 1280x720, flr 1.80x at 0.04x); `bilateral` needs only
# `color` and so is the fallback for any frame.
_PREFERENCE = ("crossregression", "kpn", "flr", "svgf", "crossreg", "bmfr", "statistical", "bilateral")


class UnknownPipelineError(KeyError):
    def __str__(self) -> str:
        return str(self.args[0])


def register(cls: type[Pipeline]) -> type[Pipeline]:
    """Class decorator adding a pipeline to the registry under `cls.name`."""
    if cls.name in _REGISTRY:
        raise ValueError(f"pipeline '{cls.name}' registered twice")
    _REGISTRY[cls.name] = cls
    return cls


def names() -> list[str]:
    return sorted(_REGISTRY)


def pipeline_class(name: str) -> type[Pipeline]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownPipelineError(f"unknown pipeline '{name}'; available: {', '.join(names())}") from None


def get(name: str, **options: Any) -> Pipeline:
    """A new pipeline object; `options` are fields of its Options dataclass."""
    return pipeline_class(name)(**options)


def describe() -> list[dict[str, Any]]:
    return [_REGISTRY[n].describe() for n in names()]


def auto(layers: set[str] | frozenset[str]) -> str:
    """Name of the preferred registered pipeline (not `auto` itself) whose required layers are all in `layers`:
    what `auto` runs on frames without the half buffers."""
    for name in (*_PREFERENCE, *names()):
        cls = _REGISTRY.get(name)
        if cls is not None and name != AUTO and set(cls.requires) <= set(layers):
            return name
    raise UnknownPipelineError(f"no pipeline can denoise a frame with layers {sorted(layers)}")


for _module in pkgutil.iter_modules(__path__):
    if _module.name not in ("base", "options"):
        importlib.import_module(f"{__name__}.{_module.name}")
