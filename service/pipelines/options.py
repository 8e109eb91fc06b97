"""Pipeline options: every field of a pipeline's frozen Options dataclass declares its type (the annotation)
and its range or choices (`option(...)`) once, and `build` is the one validator that enforces them.

`Pipeline.__init__` calls `build`, so the CLI, REST, sessions and the benchmark all refuse a bad value
before any work, with an `OptionError` naming the option and what it takes. Types are strict: an integer
option takes an integer (not 2.5, not true), a number option a finite int or float (not "abc", not null
unless the annotation allows None), a boolean option only true or false. Resource options (window
sizes, radii, thread counts) carry hard caps, so the work and memory of one frame stay bounded;
`describe` shows them (GET /v1/pipelines).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

_SPEC = "mcdenoise.option"  # dataclass field metadata key

# Hard caps of the resource options that several pipelines share. One frame's work grows with their square
# (window taps per pixel) and with its pixels. Measured at the caps, 1280x720, 2 busy cores, one frame:
# statistical radius 32 4.6 s (default 20: 1.6 s), crossregression window 31 sparsity 1 4.2 s, bmfr 3.6 s.
MAX_RADIUS = 32  # statistical filter window half-size, pixels: 65 x 65 taps (Sakai uses 20 at 720p)
MAX_WINDOW = 31  # regression window side, pixels, odd (Choi 2024 uses 17)
MAX_SPARSITY = 16  # regression centres on every n-th row and column; at most window // 2 + 1 (every pixel covered)
MAX_SIGMA2 = 1e6  # variance of a Gaussian range weight; far beyond it the weight is 1 everywhere
MIN_SIGMA2 = 1e-12  # and its least: its float32 square root, 1e-6, stays a normal number to divide by
MAX_THREADS = 32  # threads one option may ask for (ONNX Runtime, the online worker's torch)
_KINDS = {bool: "boolean", int: "integer", float: "number", str: "string"}


class OptionError(ValueError):
    """An option value a pipeline refuses; `option` names it."""

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


@dataclass(frozen=True)
class Spec:
    """The values one option takes besides its type: bounds (inclusive `low`/`high`, exclusive
    `above`/`below`), oddness, or a closed set of strings (`choices`: a tuple, or a function returning
    one when the set is known only at run time, like the weight registry)."""

    low: float | None = None
    high: float | None = None
    above: float | None = None
    below: float | None = None
    odd: bool = False
    choices: tuple[str, ...] | Callable[[], tuple[str, ...]] | None = None

    def allowed(self) -> tuple[str, ...] | None:
        return self.choices() if callable(self.choices) else self.choices


def option(
    default: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    above: float | None = None,
    below: float | None = None,
    odd: bool = False,
    choices: tuple[str, ...] | Callable[[], tuple[str, ...]] | None = None,
) -> Any:
    """A dataclass field with `default` and the range of its values (see Spec)."""
    spec = Spec(low, high, above, below, odd, choices)
    return dataclasses.field(default=default, metadata={_SPEC: spec})


@dataclass(frozen=True)
class _Field:
    name: str
    kind: type  # bool, int, float or str
    nullable: bool  # None allowed (annotation `X | None`)
    spec: Spec
    default: Any

    def text(self) -> str:
        """What the option takes, in words: 'an odd integer in [3, 31]', 'a number in (0, 1] or null'."""
        spec = self.spec
        if self.kind is bool:
            out = "true or false"
        elif self.kind is str:
            allowed = spec.allowed()
            out = "a string" if allowed is None else "one of " + ", ".join(repr(c) for c in allowed)
        else:
            out = ("an odd integer" if spec.odd else "an integer") if self.kind is int else "a number"
            if (spec.low, spec.above, spec.high, spec.below) != (None,) * 4:
                lo = f"[{_num(spec.low)}" if spec.low is not None else (
                    f"({_num(spec.above)}" if spec.above is not None else "(-inf")
                hi = f"{_num(spec.high)}]" if spec.high is not None else (
                    f"{_num(spec.below)})" if spec.below is not None else "inf)")
                out += f" in {lo}, {hi}"
        return out + (" or null" if self.nullable else "")

    def check(self, value: Any, who: str) -> Any:
        """`value` as the option's type; OptionError naming the option otherwise."""
        if value is None and self.nullable:
            return None
        if self.kind is bool:
            ok = isinstance(value, bool)
        elif self.kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif self.kind is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool) and _finite(value)
            value = float(value) if ok else value
        else:
            ok = isinstance(value, str)
        ok = ok and self._in_range(value)
        if not ok:
            raise OptionError(f"option '{self.name}' of {who} must be {self.text()}, got {_shown(value)}", self.name)
        return value

    def _in_range(self, value: Any) -> bool:
        spec = self.spec
        if self.kind is str:
            allowed = spec.allowed()
            return allowed is None or value in allowed
        if self.kind is bool:
            return True
        return ((spec.low is None or value >= spec.low) and (spec.high is None or value <= spec.high)
                and (spec.above is None or value > spec.above) and (spec.below is None or value < spec.below)
                and (not spec.odd or value % 2 == 1))

    def describe(self) -> dict[str, Any]:
        """JSON-schema-like description: type, default, bounds, enum, nullable, and the same in words."""
        spec = self.spec
        out: dict[str, Any] = {"type": _KINDS[self.kind], "default": self.default}
        for key, value in (("minimum", spec.low), ("maximum", spec.high), ("exclusiveMinimum", spec.above),
                           ("exclusiveMaximum", spec.below)):
            if value is not None:
                out[key] = value
        if spec.odd:
            out["odd"] = True
        if self.kind is str and spec.allowed() is not None:
            out["enum"] = list(spec.allowed() or ())
        if self.nullable:
            out["nullable"] = True
        out["allowed"] = self.text()
        return out


def fields(options_cls: type) -> list[_Field]:
    """The declared options of an Options dataclass, in order. Raises TypeError for a field without
    `option(...)` or of a type other than bool, int, float, str (optionally `| None`)."""
    hints = typing.get_type_hints(options_cls)
    out = []
    for f in dataclasses.fields(options_cls):
        spec = f.metadata.get(_SPEC)
        if spec is None:
            raise TypeError(f"{options_cls.__name__}.{f.name} declares no range: use options.option(...)")
        kind, nullable = _kind(hints[f.name])
        out.append(_Field(f.name, kind, nullable, spec, f.default))
    return out


def build(options_cls: type, values: Mapping[str, Any], who: str) -> Any:
    """An instance of the frozen Options dataclass `options_cls` from `values`, every value checked.

    who: names the pipeline in messages ("pipeline 'flr'"). Raises OptionError naming the first unknown
    option or the first value outside its declared type and range; a relation between options (checked
    by the dataclass's __post_init__) raises OptionError too.
    """
    declared = fields(options_cls)
    unknown = sorted(set(values) - {f.name for f in declared})
    if unknown:
        shown = ", ".join(_shown(name) for name in unknown[:5]) + (", ..." if len(unknown) > 5 else "")
        raise OptionError(f"{who} has no option {shown}; options: "
                          f"{', '.join(sorted(f.name for f in declared)) or 'none'}", str(unknown[0])[:64])
    checked = {f.name: f.check(values[f.name], who) for f in declared if f.name in values}
    try:
        return options_cls(**checked)
    except OptionError as err:  # a relation between options (__post_init__)
        raise OptionError(f"{who}: {err}", err.option) from None


def _finite(value: int | float) -> bool:
    """Whether `value` is a finite float or an int that a float holds (JSON's integers have no bound)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def check_sparsity(window: int, sparsity: int) -> None:
    """The relation of a block regression's options (regression.terms.BlockParams): every pixel needs a
    centre within the window's half-size, so sparsity <= window // 2 + 1."""
    if sparsity > window // 2 + 1:
        raise OptionError(f"option 'sparsity' must be at most window // 2 + 1 = {window // 2 + 1} "
                          f"(window {window}), got {sparsity}", "sparsity")


def describe(options_cls: type) -> dict[str, dict[str, Any]]:
    """option name -> `_Field.describe()`, for /v1/pipelines and `python -m service pipelines`."""
    return {f.name: f.describe() for f in fields(options_cls)}


def _kind(annotation: Any) -> tuple[type, bool]:
    args = typing.get_args(annotation)
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1 and len(args) == 2 and rest[0] in _KINDS:
            return rest[0], True
    elif annotation in _KINDS:
        return annotation, False
    raise TypeError(f"option type {annotation!r} is not one of bool, int, float, str (optionally | None)")


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _shown(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."
