"""Training windows for the offline-trained networks, cut from rendered sequence folders (models.data).

A `SequenceBank` holds every frame of the given folders in memory, already split the way the serving
pipeline splits them: emission subtracted from the noisy radiance and from the reference (Pipeline.step
does the same before `denoise`), demodulated by the albedo. A `Window` is what one training example is:
T consecutive frames of one sequence, as float32 torch tensors.

Sampling (`SequenceBank.sample`), following Chaitanya 2017 sec. 4.3:
- a random sequence and a random start; forward or backward playback at random;
- a random square crop whose side is a multiple of the network's alignment;
- a random rotation by 0/90/180/270 degrees;
- a random modulation in [0, 2] of each colour channel, applied to the whole window;
- which noisy estimate feeds the network: the full `color` (p = 1/2) or one half buffer, `colorA` or
  `colorB` (p = 1/4 each: half the samples). This stretches the sample counts the set covers downwards
  (2-8 spp renders give 1-8 spp inputs);
- the roughness plane replaced by ROUGHNESS_ABSENT (p = ROUGHNESS_DROP), as a frame without the optional
  `roughness` layer gives it. The paper's camera stops (same frame, new noise) are not
  sampled: our sequences carry one noise realisation per frame and half of it is in the other buffer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from service.exr import list_sequence, read_frame
from service.stages.albedo import remodulate
from service.stages.emission import subtract_emission
from service.stages.rae_inputs import GUIDE_PLANES, ROUGHNESS_ABSENT, demodulated, guide_planes

NOISY = ("color", "colorA", "colorB")  # the estimates a window may take its noisy input from
NOISY_P = (0.5, 0.25, 0.25)
ROUGHNESS_DROP = 0.2  # share of windows that see no roughness
WINDOW_FIELDS = ("noisy", "target", "guides", "motion", "motion_dual")  # also the Sequence planes they are cut from


@dataclass
class Sequence:
    """One sequence folder in memory (F frames of H x W). Radiance without emission, demodulated."""

    name: str
    noisy: np.ndarray  # (3, F, 3, H, W) float32: color, colorA, colorB demodulated, >= 0
    target: np.ndarray  # (F, 3, H, W) float32 reference demodulated, >= 0
    guides: np.ndarray  # (F, 5, H, W) float32: normal (3), log1p relative depth (1), roughness (1)
    albedo: np.ndarray  # (F, 3, H, W) float32 remodulation factor (service.stages.albedo.remodulate of 1)
    emission: np.ndarray  # (F, 3, H, W) float32 emission layer (zeros when absent)
    motion: np.ndarray  # (F, 2, H, W) float32 backward motion, pixels (zeros when absent)
    motion_dual: np.ndarray  # (F, 2, H, W) float32 `motionDual`, pixels (`motion` where absent)
    reference: np.ndarray  # (F, 3, H, W) float32 reference radiance (with emission), for validation scores

    @property
    def frames(self) -> int:
        return self.target.shape[0]


def _planes(arr: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(arr.transpose(2, 0, 1), np.float32)


def load_sequence(folder: str | Path) -> Sequence:
    """Read a rendered folder (every frame needs color, colorA, colorB, albedo, normal, depth, reference)."""
    folder = Path(folder)
    noisy, target, guides, albedo, emission, motion, dual, reference = [], [], [], [], [], [], [], []
    for path in list_sequence(folder):
        frame = read_frame(path)
        missing = [k for k in (*NOISY, "albedo", "normal", "depth", "reference") if k not in frame]
        if missing:
            raise ValueError(f"{path}: training frames need layers {missing}")
        h, w = frame.height, frame.width
        split = [frame[k] for k in (*NOISY, "reference")]
        emit = frame.get("emission")
        if emit is None:
            emit = np.zeros((h, w, 3), np.float32)
        else:  # the inputs as Pipeline.denoise_split takes it (its clip at an emitter's edge); the target exact
            split = subtract_emission(split[:3], emit) + [split[3] - emit]
        noisy.append([_planes(demodulated(x, frame["albedo"])) for x in split[:-1]])
        target.append(_planes(demodulated(split[-1], frame["albedo"])))
        guides.append(guide_planes(frame["normal"], frame["depth"], frame.get("roughness")))
        albedo.append(_planes(remodulate(np.ones((h, w, 3), np.float32), frame["albedo"])))
        emission.append(_planes(emit))
        move = frame.get("motion")
        motion.append(_planes(np.zeros((h, w, 2), np.float32) if move is None else move))
        dual.append(_planes(frame["motionDual"]) if "motionDual" in frame else motion[-1])
        reference.append(_planes(frame["reference"]))
    if not target:
        raise ValueError(f"{folder}: no frames")
    return Sequence(folder.name, np.stack(noisy, axis=1), np.stack(target), np.stack(guides), np.stack(albedo),
                    np.stack(emission), np.stack(motion), np.stack(dual), np.stack(reference))


def sequence_folders(root: str | Path) -> list[Path]:
    """The sequence folders under `root` (those with a sequence.json), sorted; `root` itself if it is one."""
    root = Path(root)
    if (root / "sequence.json").is_file():
        return [root]
    return sorted(p.parent for p in root.glob("*/sequence.json"))


@dataclass
class Window:
    """A training example: T frames, as torch tensors (batch axis added by `collate`)."""

    noisy: torch.Tensor  # (T, 3, S, S) demodulated noisy radiance, linear, >= 0
    target: torch.Tensor  # (T, 3, S, S) demodulated reference, linear, >= 0
    guides: torch.Tensor  # (T, 5, S, S) normal, log1p relative depth, roughness
    motion: torch.Tensor  # (T, 2, S, S) backward motion in pixels, in the window's orientation
    motion_dual: torch.Tensor  # (T, 2, S, S) dual motion vectors (`motionDual`), the same way


def _rotate_motion(motion: torch.Tensor, k: int) -> torch.Tensor:
    """(..., 2, S, S) motion (x right, y down) of an image rotated by torch.rot90(k) (counter-clockwise)."""
    mx, my = motion[..., 0, :, :], motion[..., 1, :, :]
    for _ in range(k % 4):  # a CCW quarter turn maps the displacement (x, y) to (y, -x) in image axes
        mx, my = my, -mx
    return torch.stack([mx, my], dim=-3)


class SequenceBank:
    """The sequences of a training set in memory, with the window sampler of the module docstring. The planes
    windows are cut from also sit on `device` as torch tensors (shared with the numpy arrays on the CPU), so
    that on a GPU a window is cut there and no batch crosses the bus."""

    def __init__(self, sequences: list[Sequence], device: str | torch.device = "cpu"):
        if not sequences:
            raise ValueError("no sequences")
        self.sequences = sequences
        self.device = torch.device(device)
        self._planes = [{f: torch.from_numpy(getattr(s, f)).to(self.device)
                         for f in WINDOW_FIELDS} for s in sequences]

    @classmethod
    def from_root(cls, root: str | Path, device: str | torch.device = "cpu") -> SequenceBank:
        folders = sequence_folders(root)
        if not folders:
            raise ValueError(f"{root}: no sequence folders (folders with sequence.json)")
        return cls([load_sequence(f) for f in folders], device)

    def sample(self, rng: np.random.Generator, frames: int, crop: int, *, reverse: bool = True,
               index: int | None = None) -> Window:
        """One random window of `frames` frames and a `crop` x `crop` square (module docstring), its tensors on
        the bank's device. `reverse`: allow backward playback (then the window's motion is zero: only backward
        motion is stored). index: of the sequence to cut it from (None: drawn from `rng` first)."""
        index = int(rng.integers(len(self.sequences))) if index is None else index
        seq, planes = self.sequences[index], self._planes[index]
        if seq.frames < frames:
            raise ValueError(f"sequence {seq.name} has {seq.frames} frames; windows need {frames}")
        h, w = seq.target.shape[-2:]
        if crop > min(h, w):
            raise ValueError(f"crop {crop} is larger than sequence {seq.name} ({w}x{h})")
        start = int(rng.integers(seq.frames - frames + 1))
        order = np.arange(start, start + frames)
        if reverse and rng.random() < 0.5:
            order = order[::-1]
        y, x = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
        frames_at = torch.from_numpy(order.copy()).to(self.device)
        window = (frames_at, slice(None), slice(y, y + crop), slice(x, x + crop))
        source = int(rng.choice(len(NOISY), p=NOISY_P))
        scale = torch.from_numpy(rng.uniform(0.0, 2.0, size=(1, 3, 1, 1)).astype(np.float32)).to(self.device)
        k = int(rng.integers(4))
        guides = planes["guides"][window]  # advanced indexing: a copy
        if rng.random() < ROUGHNESS_DROP:
            guides[:, GUIDE_PLANES["roughness"]] = ROUGHNESS_ABSENT
        motion, dual = planes["motion"][window], planes["motion_dual"][window]
        if order[0] > order[-1]:  # played backwards: no forward motion is stored, so none is given
            motion, dual = torch.zeros_like(motion), torch.zeros_like(dual)

        def turn(a: torch.Tensor) -> torch.Tensor:
            return torch.rot90(a, k, dims=(-2, -1)).contiguous()

        return Window(turn(planes["noisy"][source][window] * scale), turn(planes["target"][window] * scale),
                      turn(guides), turn(_rotate_motion(motion, k)), turn(_rotate_motion(dual, k)))


def collate(windows: list[Window]) -> Window:
    """Stack windows along a new batch axis 0: tensors (N, T, C, S, S)."""
    return Window(*(torch.stack([getattr(w, f) for w in windows]) for f in WINDOW_FIELDS))
