"""The training-set plan: its documented size, held-out seeds 0 and 1, spp variety, and resume by sequence.json."""

import pytest

from models.data.dataset import DatasetOptions, plan
from models.data.scenes import SCENES
from models.data.sequence import METADATA


def test_default_plan_is_every_scene_with_seeds_two_to_five(tmp_path):
    jobs = plan(tmp_path, DatasetOptions())
    assert len(jobs) == 4 * len(SCENES)
    # seed 0 (the benchmark's canonical animation) and seed 1 (hard cases) are held out
    assert {job.seed for job in jobs} == {2, 3, 4, 5}
    assert len({job.folder for job in jobs}) == len(jobs)
    assert jobs[0].folder == tmp_path / f"{next(iter(SCENES))}_s2"


def test_every_scene_is_rendered_at_more_than_one_sample_count(tmp_path):
    jobs = plan(tmp_path, DatasetOptions())
    for scene in SCENES:
        assert len({job.spp for job in jobs if job.scene == scene}) >= 2, scene
    assert {job.spp for job in jobs} == {2, 4, 8}


def test_validation_plan_starts_after_the_training_seeds(tmp_path):
    jobs = plan(tmp_path, DatasetOptions(seeds_per_scene=1, first_seed=6))
    assert {job.seed for job in jobs} == {6} and len(jobs) == len(SCENES)
    with pytest.raises(ValueError, match="held out"):
        DatasetOptions(first_seed=1)


def test_a_sequence_counts_as_done_once_its_metadata_exists(tmp_path):
    job = plan(tmp_path, DatasetOptions(seeds_per_scene=1))[0]
    job.folder.mkdir(parents=True)
    (job.folder / "frame_0000.exr").write_bytes(b"partial")
    assert not job.done
    (job.folder / METADATA).write_text("{}")
    assert job.done
