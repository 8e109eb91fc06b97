"""A pipeline run over a sequence, and the errors of what it made against the references, as the benchmark
scores them (service/metrics.py)."""

import numpy as np

from service.frame import Frame
from service.metrics import rel_l2, temporal_rel_l2


def run_sequence(pipeline, frames: list[Frame], *, fresh_each_frame: bool = False):
    """(each frame's output colour, (H, W, 3) float32; the last state) of `pipeline` over `frames` as one
    sequence, or each frame a sequence of its own with `fresh_each_frame`; the frames' `reference` withheld."""
    state, outs = None, []
    for frame in frames:
        if state is None or fresh_each_frame:
            state = pipeline.start(frame.height, frame.width)
        out, state = pipeline.step(Frame({k: v for k, v in frame.buffers.items() if k != "reference"}, {}), state)
        outs.append(out["color"])
    return outs, state


def sequence_errors(outputs: list[np.ndarray], references: list[np.ndarray], *,
                    trim: float = 0.0) -> tuple[float, float]:
    """(mean relL2 over frames, `trim` of each frame's largest pixel errors left out; mean temporal error over
    consecutive pairs) of (H, W, 3) float32 outputs."""
    spatial = np.mean([rel_l2(o, r, trim=trim) for o, r in zip(outputs, references, strict=True)])
    temporal = np.mean([temporal_rel_l2(outputs[i - 1], outputs[i], references[i - 1], references[i])
                        for i in range(1, len(outputs))])
    return float(spatial), float(temporal)
