"""Errors of a denoised sequence against its references, as the benchmark scores them (service/metrics.py)."""

import numpy as np

from service.metrics import rel_l2, temporal_rel_l2


def sequence_errors(outputs: list[np.ndarray], references: list[np.ndarray]) -> tuple[float, float]:
    """(mean relL2 over frames, mean temporal error over consecutive pairs) of (H, W, 3) float32 outputs."""
    spatial = np.mean([rel_l2(o, r) for o, r in zip(outputs, references, strict=True)])
    temporal = np.mean([temporal_rel_l2(outputs[i - 1], outputs[i], references[i - 1], references[i])
                        for i in range(1, len(outputs))])
    return float(spatial), float(temporal)
