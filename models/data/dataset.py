"""The training set: which sequences `make data` renders, and rendering them with resume and progress.

Default size (DatasetOptions()): 27 sequences (each of the 9 library scenes with variation seeds 1, 2, 3;
seed 0 stays the canonical animation used by the bundled sample and benchmarks) x 8 frames at 256x256,
4 spp noisy input, 1024 spp references. A folder counts as done when its sequence.json exists (written
last), so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from models.data.render import RenderOptions
from models.data.scenes import SCENES, get
from models.data.sequence import METADATA, render_sequence


@dataclass(frozen=True)
class DatasetOptions:
    """Size of the training set."""

    seeds_per_scene: int = 3  # variation seeds 1..n of every library scene
    frames: int = 8  # frames per sequence
    width: int = 256  # pixels
    height: int = 256  # pixels
    spp: int = 4  # noisy samples per pixel (separate 1-spp passes)
    ref_spp: int = 1024  # reference samples per pixel
    half: bool = False  # float16 EXR channels (smaller files, 10-bit mantissa)


@dataclass(frozen=True)
class Job:
    """One sequence of the set."""

    scene: str  # library scene name
    seed: int  # variation and noise seed
    folder: Path  # output folder

    @property
    def done(self) -> bool:
        return (self.folder / METADATA).is_file()


def plan(out: str | Path, opts: DatasetOptions) -> list[Job]:
    """Every sequence of the set, in render order (all scenes at seed 1, then seed 2, ...)."""
    out = Path(out)
    return [Job(name, seed, out / f"{name}_s{seed}") for seed in range(1, opts.seeds_per_scene + 1)
            for name in SCENES]


def render_dataset(out: str | Path, opts: DatasetOptions, *, progress: bool = True) -> Iterator[tuple[Job, float]]:
    """Render the jobs of `plan` that are not done; yields (job, seconds) after each sequence."""
    from tqdm import tqdm

    jobs = plan(out, opts)
    todo = [job for job in jobs if not job.done]
    bar = tqdm(total=len(todo) * opts.frames, unit="frame", disable=not progress,
               desc=f"{len(jobs) - len(todo)}/{len(jobs)} sequences already done")
    try:
        for job in todo:
            bar.set_postfix_str(job.folder.name)
            render_opts = RenderOptions(opts.width, opts.height, opts.spp, opts.ref_spp, seed=job.seed)
            seconds = render_sequence(get(job.scene), job.folder, render_opts, opts.frames, half=opts.half,
                                      on_frame=lambda _i, _s: bar.update(1))
            yield job, sum(seconds)
    finally:
        bar.close()
