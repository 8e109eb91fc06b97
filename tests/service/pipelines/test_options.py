"""service/pipelines/options.py: every option declares its type and range once; `build` refuses every value
outside them (issue 22, finding 1, 2, 3 and 6); every value inside them runs."""

from __future__ import annotations

import shutil

import pytest

from service import pipelines
from service.frame import Frame
from service.pipelines.options import OptionError, fields

# The bad values of issue 22's probe (finding 1), and the resource requests of findings 2 and 3.
BAD = [
    ("flr", "scale", 0), ("flr", "scale", -1), ("flr", "scale", 2.5), ("flr", "sigma", 0), ("flr", "sigma", "abc"),
    ("flr", "sigma", None), ("flr", "sigma", 1e308), ("bilateral", "radius", -3), ("bilateral", "sigma2_albedo", 0),
    ("bilateral", "sigma2_normal", 0), ("bilateral", "sigma2_position", 0), ("crossregression", "window", 0),
    ("crossregression", "window", 2), ("crossregression", "sparsity", 0), ("crossregression", "sparsity", 1e6),
    ("bmfr", "window", 0), ("bmfr", "window", 1), ("bmfr", "sparsity", 0), ("crossreg", "screen", "x"),
    ("crossreg", "seed", "x"), ("crossreg", "seed", -1), ("bilateral", "radius", True), ("flr", "demodulate", "no"),
    ("flr", "firefly_k", 0), ("svgf", "clamp_spread", "x"), ("svgf", "iterations", 100), ("statistical", "alpha", 0),
    ("statistical", "alpha", 1), ("statistical", "sigma2_albedo", float("nan")), ("bilateral", "radius", 1_000_000),
    ("statistical", "radius", 1000), ("crossreg", "threads", 1_000_000), ("crossreg", "threads", 1000),
    ("crossreg", "worker_threads", 1000), ("crossreg", "crop", 10**9), ("crossreg", "publish_every", 0),
    ("crossreg", "steps_per_frame", 10**6), ("crossreg", "weights", "/etc/shadow"),
    ("crossreg", "weights", "../weights/crossreg_unet"), ("crossreg", "weights", "missing.onnx"),
    # numbers a float cannot hold, or whose arithmetic would underflow
    ("flr", "sigma", 10**400), ("svgf", "alpha_color", -(10**400)), ("bilateral", "sigma2_albedo", 1e-300),
    ("bilateral", "sigma2_log_depth", 1e-13), ("statistical", "sigma2_normal", 1e-300), ("statistical", "alpha", 1e-17),
]


@pytest.mark.parametrize(("name", "option", "value"), BAD)
def test_bad_values_are_refused_naming_the_option_and_its_range(name, option, value):
    with pytest.raises(OptionError) as caught:
        pipelines.get(name, **{option: value})
    assert caught.value.option == option
    allowed = pipelines.pipeline_class(name).describe()["option_specs"][option]["allowed"]
    assert f"option '{option}' of pipeline '{name}' must be {allowed}, got " in str(caught.value)


def test_every_option_of_every_pipeline_declares_type_and_range():
    for info in pipelines.describe():
        cls = pipelines.pipeline_class(info["name"])
        assert list(info["option_specs"]) == list(info["options"])  # fields() raises for an undeclared one
        for f in fields(cls.Options):
            spec = info["option_specs"][f.name]
            assert spec["type"] in ("boolean", "integer", "number", "string") and spec["default"] == f.default
            if spec["type"] in ("integer", "number"):  # no unbounded number: every one has a cap
                assert ("maximum" in spec or "exclusiveMaximum" in spec), (info["name"], f.name)
            if spec["type"] == "string":
                assert spec["enum"], (info["name"], f.name)


def test_resource_caps():
    specs = {info["name"]: info["option_specs"] for info in pipelines.describe()}
    assert specs["bilateral"]["radius"]["maximum"] == 16 and specs["statistical"]["radius"]["maximum"] == 32
    assert specs["bmfr"]["window"]["maximum"] == specs["crossregression"]["window"]["maximum"] == 31
    assert specs["crossreg"]["threads"]["maximum"] == specs["crossreg"]["worker_threads"]["maximum"] == 32
    assert specs["crossreg"]["weights"]["enum"] == ["crossreg_unet"]


def test_types_are_strict_but_a_number_takes_an_integer():
    sigma = pipelines.get("flr", sigma=1).options.sigma
    assert sigma == 1.0 and isinstance(sigma, float)
    assert pipelines.get("flr", firefly_k=None).options.firefly_k is None  # `float | None`
    assert pipelines.get("statistical", sigma2_log_depth=None).options.sigma2_log_depth is None
    with pytest.raises(OptionError, match="must be an odd integer in"):
        pipelines.get("bmfr", window=13.0)


def test_sparsity_must_leave_no_pixel_without_a_centre():
    with pytest.raises(OptionError, match=r"pipeline 'bmfr': option 'sparsity' must be at most window // 2 \+ 1 = 3"):
        pipelines.get("bmfr", window=5, sparsity=4)
    assert pipelines.get("bmfr", window=5, sparsity=3).options.sparsity == 3


def _extremes(name: str) -> list[dict]:
    """One options dict per declared bound of each option (the others at their defaults)."""
    out = []
    for option, spec in pipelines.pipeline_class(name).describe()["option_specs"].items():
        if option in ("online", "lockstep", "worker_threads", "publish_every", "crop", "steps_per_frame"):
            continue  # the online worker needs torch; its options are checked by OnlineConfig's tests
        if spec["type"] == "boolean":
            out += [{option: True}, {option: False}]
        for key in ("minimum", "maximum"):
            if key in spec:
                value = spec[key] if spec["type"] == "number" else int(spec[key])
                extra = {"sparsity": {"window": 31}, "window": {"sparsity": 1}}.get(option, {})  # see check_sparsity
                out.append({option: value, **extra})
        for key, nudge in (("exclusiveMinimum", 1e-6), ("exclusiveMaximum", -1e-6)):
            if key in spec:
                out.append({option: spec[key] + nudge})
        if spec.get("nullable"):
            out.append({option: None})
    return out


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", pipelines.names())
def test_every_declared_bound_runs(name, tiny_layers):
    """The caps are what the stages can do: each option at each bound denoises two frames, finite."""
    frames = [Frame.from_buffers(layers) for layers in tiny_layers[:2]]
    for options in _extremes(name):
        pipeline = pipelines.get(name, **options)
        state = pipeline.start(frames[0].height, frames[0].width)
        for frame in frames:
            out, state = pipeline.step(frame, state)
        assert out["color"].shape == frames[0]["color"].shape, options


def test_weights_come_from_the_registry_and_an_operator_folder(tmp_path, monkeypatch):
    from service.runtime import SHIPPED_WEIGHTS, WEIGHTS_DIR_ENV, weight_names

    assert weight_names() == ("crossreg_unet", "flnr", "kpn", "rae")
    assert weight_names("crossreg_unet") == ("crossreg_unet",)
    shutil.copy(SHIPPED_WEIGHTS / "crossreg_unet.onnx", tmp_path / "site_tuned.onnx")
    (tmp_path / "not_a_model.onnx").write_bytes(b"not onnx")
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))
    assert weight_names() == ("crossreg_unet", "flnr", "kpn", "not_a_model", "rae", "site_tuned")
    # a file that is not a model is offered to every network, so that choosing it says what is wrong
    assert weight_names("crossreg_unet") == ("crossreg_unet", "not_a_model", "site_tuned")
    assert weight_names("rae") == ("not_a_model", "rae")
    pipeline = pipelines.get("crossreg", weights="site_tuned")
    assert pipeline.start(8, 8).model is not None
    with pytest.raises(OptionError, match="weights 'not_a_model' are not a loadable ONNX model") as caught:
        pipelines.get("crossreg", weights="not_a_model").start(8, 8)
    assert caught.value.option == "weights"
