"""The scene library: enough scenes, each animated, covering the required lights, meshes and textures."""

import numpy as np
import pytest

from models.data import scenes
from models.data.description import Texture


def _uses_texture(value) -> bool:
    if isinstance(value, Texture):
        return True
    if isinstance(value, dict):
        return any(_uses_texture(v) for v in value.values())
    return False


@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_every_scene_animates_camera_and_objects(name):
    spec = scenes.get(name)
    for seed in (0, 2):
        a, b = spec.build(0.0, seed), spec.build(1.0, seed)
        names = [s.name for s in a.shapes]
        assert len(set(names)) == len(names) and names == [s.name for s in b.shapes]
        assert a.camera.origin != b.camera.origin or a.camera.target != b.camera.target
        assert any(not np.allclose(s.to_world, t.to_world) for s, t in zip(a.shapes, b.shapes, strict=True))
        for s in a.shapes:
            assert 0.0 <= s.roughness <= 1.0


def test_library_covers_the_stress_cases_and_building_blocks():
    assert len(scenes.SCENES) >= 8
    states = [spec.build(0.0, 0) for spec in scenes.SCENES.values()]
    shapes = [s for st in states for s in st.shapes]
    lights = {light["type"] for st in states for light in st.lights}
    assert {"point", "spot", "envmap"} <= lights
    assert any(s.radiance is not None for s in shapes)  # area lights
    assert any(s.kind == "mesh" for s in shapes)  # meshes from numpy
    assert any(_uses_texture(s.bsdf) for s in shapes)  # bitmap textures from numpy arrays
    assert {"sphere", "cube", "rectangle", "cylinder"} <= {s.kind for s in shapes}  # built-in shapes
    for required in ("shadows", "disocclusion", "fireflies", "indirect", "textures", "thin", "dark", "emissive"):
        assert required in scenes.SCENES


def test_seed_zero_is_the_canonical_animation_and_unknown_names_are_refused():
    assert scenes.variation(0) == scenes.Variation(0.0, 1.0, 0.0, 1.0)
    assert scenes.variation(1) != scenes.variation(2)
    with pytest.raises(ValueError, match="unknown scene 'nope'; scenes: shadows"):
        scenes.get("nope")


def render_scene(name: str) -> dict[str, float]:
    """Frame 0 of library scene `name`, tiny: whether every layer is finite, and the reference mean."""
    from models.data.render import RenderOptions, previous_of, render_frame
    from models.data.variant import load_mitsuba

    mi = load_mitsuba()
    spec = scenes.get(name)
    opts = RenderOptions(24, 16, 2, 4, gbuffer_spp=1, emission_spp=1, ao_spp=1)
    frame = render_frame(mi, spec, 0, opts, previous_of(mi, spec, 0, opts))
    return {"finite": float(all(np.isfinite(v).all() for v in frame.layers.values())),
            "reference_mean": float(frame.layers["reference"].mean())}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_every_scene_renders(name):
    pytest.importorskip("mitsuba")
    from tests.models.data.isolated import render_or_fail

    result = render_or_fail(render_scene, name)  # in a child process: a native abort fails this test only
    assert result["finite"] == 1.0
    assert result["reference_mean"] > 0


def test_scene_clock_is_the_frame_time_up_to_the_period_then_a_continuous_triangle_wave():
    from models.data.description import scene_clock

    assert [scene_clock(t, 0.0) for t in (-1.0, 5.0, 100.0)] == [-1.0, 5.0, 100.0]
    assert [scene_clock(t, 8.0) for t in (-1.0, 0.0, 8.0, 9.0, 16.0, 17.0, 24.0, 25.0)] == \
        [-1.0, 0.0, 8.0, 7.0, 0.0, 1.0, 8.0, 7.0]
    t = np.linspace(0.0, 100.0, 2001)
    clock = np.array([scene_clock(x, 8.0) for x in t])
    assert np.abs(np.diff(clock)).max() <= np.diff(t).max() + 1e-12  # continuous, never faster than time
    assert clock.min() >= 0.0 and clock.max() <= 8.0


@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_long_sequences_keep_moving_within_the_designed_frames(name):
    """Every scene at frames 0..63 (the long benchmark): consecutive frames differ, and a periodic scene is
    its own animation within the period."""
    spec = scenes.get(name)
    origins = [spec.state(float(t), 0).camera.origin for t in range(64)]
    assert all(a != b for a, b in zip(origins, origins[1:], strict=False))
    if spec.period:
        t = spec.period / 2
        assert spec.state(t, 0).camera.origin == spec.build(t, 0).camera.origin
