"""The Mitsuba renderer: every layer of a tiny sequence, and the motion-vector proofs on rendered frames.

Renders are tiny (32x32 to 48x48, 2 frames, few samples) so the file runs in seconds on 2 busy cores with
the llvm variant (the first run compiles kernels into Dr.Jit's cache). Every render runs in a child
process (tests.models.data.isolated), so a native abort in the renderer fails these tests, not the suite.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from models.data import scenes  # noqa: E402
from models.data.__main__ import main  # noqa: E402
from models.data.camera import pixel_centres, project_points  # noqa: E402
from models.data.evaluate import sequence_report  # noqa: E402
from models.data.motion import DEPTH_MISS, silhouette  # noqa: E402
from models.data.render import RenderOptions, previous_of, render_emission, render_frame  # noqa: E402
from models.data.variant import load_mitsuba  # noqa: E402
from service.exr import list_sequence, read_frame  # noqa: E402
from service.frame import DIAGNOSTICS, LAYERS  # noqa: E402
from service.metrics import rel_l2_map  # noqa: E402
from service.stages.reprojection import reproject  # noqa: E402
from tests.models.data import probe_scenes  # noqa: E402
from tests.models.data.isolated import render_or_fail  # noqa: E402

# Warping the previous reference by the motion vectors must remove most of the frame-to-frame error
# (the rest is reference noise at 128 spp and bilinear resampling): at most this fraction of the
# unwarped error, away from disocclusions and silhouettes.
WARP_ERROR_RATIO = 0.2
WARP_ERROR_MAX = 0.015  # relL2 of warped vs current reference over the same pixels
# Two emission passes with different seeds differ by at most this fraction of the brightest pixel. Where a
# small light covers part of a pixel, 16 samples differed by 0.29, 64 by 0.094 and 256 by 0.025 (fireflies, 48x48).
EMISSION_SEED_SPREAD = 0.05


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "emissive"
    code = render_or_fail(main, ["render", "--scene", "emissive", "--frames", "2", "--spp", "2", "--ref-spp", "8",
                                 "--size", "32x24", "--seed", "1", "--out", str(out)])
    assert code == 0
    return out


def test_cli_writes_every_layer_and_metadata(tiny_sequence):
    files = list_sequence(tiny_sequence)
    assert [f.name for f in files] == ["frame_0000.exr", "frame_0001.exr"]
    frame = read_frame(files[1])
    assert set(frame.buffers) == set(LAYERS) - set(DIAGNOSTICS)
    assert (frame.height, frame.width) == (24, 32)
    assert frame.nonfinite_total == 0
    meta = json.loads((tiny_sequence / "sequence.json").read_text())
    assert meta["spp"] == 2 and meta["ref_spp"] == 8 and meta["size"] == [32, 24] and len(meta["frames"]) == 2
    for key in ("world_to_camera", "projection", "fov_x", "objects"):
        assert key in meta["frames"][0]
    assert np.asarray(meta["frames"][0]["world_to_camera"]).shape == (4, 4)
    assert set(meta["frames"][0]["objects"]) >= {"floor", "tube", "glow0"}


def test_layers_are_physically_plausible(tiny_sequence):
    f = read_frame(list_sequence(tiny_sequence)[1])
    np.testing.assert_allclose(f["color"], 0.5 * (f["colorA"] + f["colorB"]), rtol=1e-5, atol=1e-6)
    assert not np.array_equal(f["colorA"], f["colorB"])  # disjoint halves of the samples
    assert np.all(f["sampleCount"] == 2)
    assert np.all(f["bcM2"] >= 0)
    assert 0.0 <= f["albedo"].min() and f["albedo"].max() <= 1.0
    assert 0.0 <= f["ao"].min() and f["ao"].max() <= 1.0
    assert np.all((f["roughness"] >= 0) & (f["roughness"] <= 1))
    length = np.linalg.norm(f["normal"], axis=-1)
    assert np.all((np.abs(length - 1) < 1e-3) | (length == 0))
    missed = f["depth"][..., 0] >= DEPTH_MISS
    np.testing.assert_array_equal(length[missed], 0.0)
    assert np.all(f["depth"][~missed] > 0)
    # Emission is noise-free and part of the radiance: the glowing spheres are seen directly.
    assert f["emission"].max() > 1.0
    assert f["emission"].min() >= 0 and f["emission"].sum() < f["reference"].sum()
    assert f["reference"].mean() == pytest.approx(f["color"].mean(), rel=0.5)


def test_report_on_the_cli_output(tiny_sequence):
    report = sequence_report(tiny_sequence)
    assert report["noisy_rel_l2"] > 0 and report["seconds_per_frame"] > 0
    assert np.isfinite(report["motion"])


def emission_of_two_seeds(scene: str, size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """The emission pass of frame 0 of scenes.<scene> (variation 1) at RenderOptions' emission_spp, with the
    noise seeds 1 and 2."""
    state = scenes.SCENES[scene].state(0.0, 1)
    mi = load_mitsuba()
    first, second = (render_emission(mi, state, RenderOptions(size, size, 2, 1, seed=seed), 0) for seed in (1, 2))
    return first, second


def test_emission_is_noise_free_at_the_edges_of_a_small_light():
    first, second = render_or_fail(emission_of_two_seeds, "fireflies")
    brightest = max(first.max(), second.max())
    assert brightest > 100  # the light of radiance ~2.7e3 is seen
    assert np.abs(first - second).max() <= EMISSION_SEED_SPREAD * brightest


def path_split_by_depth(scene: str, size: int = 32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame 0 of scenes.<scene> by the path tracer, the same with directly seen emitters hidden, and at
    max_depth 1, each 8 independent samples with one seed."""
    from models.data.mitsuba_scene import build_scene

    spec, mi = scenes.SCENES[scene], load_mitsuba()
    state = spec.state(0.0, 1)
    images = []
    for integrator in ({"max_depth": spec.max_depth}, {"max_depth": spec.max_depth, "hide_emitters": True},
                       {"max_depth": 1}):
        built = build_scene(state, size, size, {"type": "path", **integrator}, {"type": "independent"})
        images.append(np.array(mi.render(built, spp=8, seed=3), np.float32)[..., :3])
    return tuple(images)


@pytest.mark.parametrize("scene", ["fireflies", "window"])
def test_hidden_emitters_remove_exactly_the_depth_one_radiance(scene):
    """What the reference rests on: the path tracer's radiance = the same with directly seen emitters hidden
    + its directly seen emission, sample by sample (same seed)."""
    full, hidden, direct = render_or_fail(path_split_by_depth, scene)
    assert direct.max() > 100  # a light or sky of radiance ~1e3 is seen
    np.testing.assert_allclose(hidden + direct, full, rtol=1e-3, atol=1e-3 * full.max())


def render_pair(scene: str, size: int = 48):
    """Frames 0 and 1 of probe_scenes.<scene> (runs in the child process of render_or_fail)."""
    spec = getattr(probe_scenes, scene)
    mi = load_mitsuba()
    opts = RenderOptions(size, size, 2, 128, gbuffer_spp=4, emission_spp=4, ao_spp=4)
    first = render_frame(mi, spec, 0, opts, previous_of(mi, spec, 0, opts))
    second = render_frame(mi, spec, 1, opts, (first.gbuffer, first.view))
    return first, second


@pytest.fixture(scope="module")
def camera_pair():
    return render_or_fail(render_pair, "MOVING_CAMERA")


@pytest.fixture(scope="module")
def object_pair():
    return render_or_fail(render_pair, "MOVING_OBJECT")


def test_pixel_centre_positions_project_onto_their_pixels(camera_pair):
    _, frame = camera_pair
    hit = frame.gbuffer.shape >= 0
    xy, front = project_points(frame.view.world_to_pixel, frame.gbuffer.position)
    assert hit.mean() > 0.9 and front[hit].all()
    np.testing.assert_allclose(xy[hit], pixel_centres(48, 48)[hit], atol=2e-3)


def _warp_check(pair):
    before, now = pair
    ref, prev_ref = now.layers["reference"], before.layers["reference"]
    warped, inside = reproject(prev_ref, now.layers["motion"])
    disoccluded = np.linalg.norm(now.layers["motionDual"] - now.layers["motion"], axis=-1) > 1e-3
    away = inside & ~disoccluded & ~silhouette(now.gbuffer.shape) & ~silhouette(before.gbuffer.shape)
    assert away.mean() > 0.6
    warped_error = rel_l2_map(warped, ref)[away].mean()
    static_error = rel_l2_map(prev_ref, ref)[away].mean()
    assert warped_error < WARP_ERROR_RATIO * static_error
    assert warped_error < WARP_ERROR_MAX
    return disoccluded


def test_motion_vectors_warp_the_previous_reference_for_a_moving_camera(camera_pair):
    assert np.abs(camera_pair[1].layers["motion"]).max() > 2.0  # the camera really moves
    _warp_check(camera_pair)


def test_motion_vectors_warp_the_previous_reference_for_a_moving_object(object_pair):
    motion = object_pair[1].layers["motion"]
    box = object_pair[1].gbuffer.shape == 2
    assert np.abs(motion[~box]).max() < 1e-3 and np.abs(motion[box, 0]).min() > 2.0  # only the box moves
    _warp_check(object_pair)


def _dilate(mask: np.ndarray, r: int = 1) -> np.ndarray:
    out = mask.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out |= np.roll(np.roll(mask, dy, 0), dx, 1)
    return out


def test_dual_motion_differs_only_where_the_object_uncovered_background(object_pair):
    before, now = object_pair
    disoccluded = np.linalg.norm(now.layers["motionDual"] - now.layers["motion"], axis=-1) > 1e-3
    # Static camera: background pixels now that showed the box in the previous frame.
    uncovered = (now.gbuffer.shape != 2) & (before.gbuffer.shape == 2)
    assert uncovered.sum() >= 20
    assert np.all(disoccluded <= _dilate(uncovered))
    assert (disoccluded & uncovered).sum() >= 0.9 * uncovered.sum()
    # There, the dual vectors fetch background: closer to the current reference than the motion vectors.
    ref, prev_ref = now.layers["reference"], before.layers["reference"]
    dual_error = rel_l2_map(reproject(prev_ref, now.layers["motionDual"])[0], ref)[disoccluded].mean()
    motion_error = rel_l2_map(reproject(prev_ref, now.layers["motion"])[0], ref)[disoccluded].mean()
    assert dual_error < 0.8 * motion_error


def test_dual_motion_differs_only_near_silhouettes_for_a_moving_camera(camera_pair):
    before, now = camera_pair
    disoccluded = np.linalg.norm(now.layers["motionDual"] - now.layers["motion"], axis=-1) > 1e-3
    near_edges = _dilate(silhouette(now.gbuffer.shape) | silhouette(before.gbuffer.shape), 3)
    assert disoccluded.any() and np.all(disoccluded <= near_edges)


def test_library_lists_at_least_eight_scenes(capsys):
    assert main(["scenes"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == len(scenes.SCENES) >= 8
