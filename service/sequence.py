"""Denoise a sequence folder frame by frame through one pipeline state: the loop behind the CLI and demo."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.dialects import ChannelMap
from service.exr import paired_sequence, read_frame, read_header, read_layers, write_frame, write_with_input
from service.frame import OUTPUT_LAYERS, Frame, FrameError, from_two_renders
from service.metrics import TRIM_FRACTION, rel_l2
from service.pipelines import Pipeline
from service.preview import write_preview


@dataclass(frozen=True)
class FrameResult:
    """What one denoised frame cost and achieved."""

    name: str  # input file name, reused for the output
    ms: float  # wall time of pipeline.step, milliseconds
    nonfinite: int  # NaN/Inf values repaired in the input
    rel_l2_noisy: float | None  # relL2 (0.1% trimmed) of the input `color` vs `reference`, if present
    rel_l2_out: float | None  # relL2 (0.1% trimmed) of the output vs `reference`, if present
    online: dict[str, Any] | None = None  # online-training status after this frame, for pipelines that train


def denoise_folder(
    pipeline: Pipeline, in_dir: str | Path, out_dir: str | Path, *, png: bool = False,
    channel_map: ChannelMap | None = None, view_layer: str | None = None, second_half: str | Path | None = None,
    keep_layers: bool = False,
) -> Iterator[FrameResult]:
    """Denoise every frame of `in_dir` in order; write `out_dir/<name>` (layer `color`, float32) and,
    with `png`, `out_dir/<stem>.png` previews. Yields one FrameResult per frame as it completes. Frames
    are read in their dialect (`service.exr.read_header`: `channel_map`, Blender `view_layer`). With
    `second_half`, a folder of a second render of the same frames (another seed), frame i of each makes
    the halves of frame i (`service.frame.from_two_renders`). With `keep_layers`, each output file is its
    input file plus the result, named for the input's dialect (`service.exr.write_with_input`).

    Raises FrameError (naming the file and layer) on the first bad frame. The sequence state is closed at
    the end (stopping an online-training worker, if any).
    """
    out_dir = Path(out_dir)
    state = None
    try:
        for path, second in paired_sequence(in_dir, second_half):
            try:
                header = read_header(path, channel_map, view_layer)
                frame = Frame.from_buffers(read_layers(path, header))
                if second is not None:
                    try:
                        other = read_frame(second, channel_map=channel_map, view_layer=view_layer)
                    except FrameError as err:
                        raise FrameError(f"second render {second}: {err}", err.layer) from err
                    frame = from_two_renders(frame, other)
                if state is None:
                    state = pipeline.start(frame.height, frame.width)
                start = time.perf_counter()
                out, state = pipeline.step(frame, state)
                ms = 1e3 * (time.perf_counter() - start)
            except FrameError as err:
                raise FrameError(f"{path.name}: {err}", err.layer) from err
            if keep_layers:
                write_with_input(out_dir / path.name, path, out["color"], header.mapping)
            else:
                write_frame(out_dir / path.name, {k: out[k] for k in OUTPUT_LAYERS if k in out})
            if png:
                write_preview(out_dir / f"{path.stem}.png", out["color"])
            reference = frame.get("reference")
            yield FrameResult(
                path.name,
                ms,
                frame.nonfinite_total,
                None if reference is None else rel_l2(frame["color"], reference, trim=TRIM_FRACTION),
                None if reference is None else rel_l2(out["color"], reference, trim=TRIM_FRACTION),
                getattr(state, "online_status", None),
            )
    finally:
        if state is not None:
            state.close()
