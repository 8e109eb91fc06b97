"""The training-set plan: its documented size, held-out seed 0, and resume by sequence.json."""

from models.data.dataset import DatasetOptions, plan
from models.data.scenes import SCENES
from models.data.sequence import METADATA


def test_default_plan_is_every_scene_with_seeds_one_to_three(tmp_path):
    jobs = plan(tmp_path, DatasetOptions())
    assert len(jobs) == 3 * len(SCENES)
    assert {job.seed for job in jobs} == {1, 2, 3}  # seed 0 (the canonical animation) is held out
    assert len({job.folder for job in jobs}) == len(jobs)
    assert jobs[0].folder == tmp_path / f"{next(iter(SCENES))}_s1"


def test_a_sequence_counts_as_done_once_its_metadata_exists(tmp_path):
    job = plan(tmp_path, DatasetOptions(seeds_per_scene=1))[0]
    job.folder.mkdir(parents=True)
    (job.folder / "frame_0000.exr").write_bytes(b"partial")
    assert not job.done
    (job.folder / METADATA).write_text("{}")
    assert job.done
