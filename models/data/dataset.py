"""The training set: which sequences `make data` renders, and rendering them with resume and progress.

Default size (DatasetOptions()): 44 sequences (each of the 11 library scenes with variation seeds 2..5)
x 8 frames at 128x128, 2, 4 or 8 spp noisy input (cycled over the sequences), 1024 spp references.
Held out: seed 0 (the canonical animation of the bundled sample and the benchmark) and seed 1 (the
hard-case suite's `caustics` and `window_1spp`). A folder counts as done when its sequence.json exists
(written last), so an interrupted run resumes where it stopped. The validation set of models.train is the
same plan from seed 6 with one sequence per scene (`make data`).
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

    seeds_per_scene: int = 4  # variation seeds of every library scene
    frames: int = 8  # frames per sequence
    width: int = 128  # pixels
    height: int = 128  # pixels
    spp: tuple[int, ...] = (2, 4, 8)  # noisy samples per pixel, cycled over the jobs (separate 1-spp passes)
    ref_spp: int = 1024  # reference samples per pixel
    half: bool = False  # float16 EXR channels (smaller files, 10-bit mantissa)
    first_seed: int = 2  # variation seeds first_seed, first_seed + 1, ... (0 and 1 are held out)

    def __post_init__(self):
        if self.first_seed < 2:
            raise ValueError(f"first_seed must be >= 2 (seeds 0 and 1 are held out), got {self.first_seed}")


@dataclass(frozen=True)
class Job:
    """One sequence of the set."""

    scene: str  # library scene name
    seed: int  # variation and noise seed
    spp: int  # noisy samples per pixel
    folder: Path  # output folder

    @property
    def done(self) -> bool:
        return (self.folder / METADATA).is_file()


def plan(out: str | Path, opts: DatasetOptions) -> list[Job]:
    """Every sequence of the set, in render order (all scenes at the first seed, then the next, ...)."""
    out = Path(out)
    pairs = [(name, seed) for seed in range(opts.first_seed, opts.first_seed + opts.seeds_per_scene) for name in SCENES]
    return [Job(name, seed, opts.spp[i % len(opts.spp)], out / f"{name}_s{seed}")
            for i, (name, seed) in enumerate(pairs)]


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
            render_opts = RenderOptions(opts.width, opts.height, job.spp, opts.ref_spp, seed=job.seed)
            seconds = render_sequence(get(job.scene), job.folder, render_opts, opts.frames, half=opts.half,
                                      on_frame=lambda _i, _s: bar.update(1))
            yield job, sum(seconds)
    finally:
        bar.close()
