"""Per-pixel online sample statistics after a Box-Cox transform (Sakai et al. 2024, Algorithm 1, eq. 15).

For renderers that hand individual samples instead of the `sampleCount`/`bcMean`/`bcM2`/`bcM3`
layers. Statistics follow the frame format: mean, and central moments M2 = sum(d^2)/n and
M3 = sum(d^3)/n of the transformed samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOX_COX_LAMBDA = 0.5  # Sakai 2024 sec. 5: lambda = 1/2


def box_cox(x: np.ndarray, lam: float = BOX_COX_LAMBDA) -> np.ndarray:
    """Box-Cox transform, eq. 15: (x^lam - 1) / lam, or log x for lam = 0.

    x: radiance samples, any shape, float32. Negative radiance (legal input) goes through the odd
    extension sign(x) |x|^lam so the transform stays finite and monotonic.
    """
    x = np.asarray(x, dtype=np.float32)
    if lam == 0.0:
        return np.log(np.maximum(x, np.float32(1e-12)))
    powered = np.sign(x) * np.power(np.abs(x), np.float32(lam))
    return (powered - np.float32(1.0)) / np.float32(lam)


@dataclass
class SampleStatistics:
    """Running statistics per pixel: n (H, W, 1), mean/M2/M3 (H, W, C), all float32.

    `m2_sum` and `m3_sum` are the un-normalised sums of Algorithm 1 (hat M); the frame-format layers
    are `m2_sum / n` and `m3_sum / n`.
    """

    n: np.ndarray
    mean: np.ndarray
    m2_sum: np.ndarray
    m3_sum: np.ndarray

    @classmethod
    def empty(cls, height: int, width: int, channels: int = 3) -> SampleStatistics:
        zeros = np.zeros((height, width, channels), np.float32)
        return cls(np.zeros((height, width, 1), np.float32), zeros, zeros.copy(), zeros.copy())

    def add(self, sample: np.ndarray, lam: float = BOX_COX_LAMBDA) -> None:
        """Fold in one sample per pixel (Algorithm 1: Welford for the mean and M2).

        The M3 update is Terriberry's (the one Meng 2015 derives): the paper's printed form
        differs from it for n >= 2 and does not match a two-pass computation, which this does.
        sample: (H, W, C) float32 radiance of one sample (one 1-spp pass).
        """
        x = box_cox(sample, lam)
        self.n += 1.0
        n = self.n
        delta = x - self.mean
        delta_n = delta / n
        term = delta * delta_n * (n - 1.0)
        self.mean += delta_n
        # M3 uses the old M2, so it is updated first.
        self.m3_sum += term * delta_n * (n - 2.0) - 3.0 * delta_n * self.m2_sum
        self.m2_sum += term

    def layers(self) -> dict[str, np.ndarray]:
        """Frame-format layers `sampleCount`, `bcMean`, `bcM2`, `bcM3` (float32, shapes as above)."""
        n = np.maximum(self.n, 1.0)
        return {
            "sampleCount": self.n.copy(),
            "bcMean": self.mean.copy(),
            "bcM2": self.m2_sum / n,
            "bcM3": self.m3_sum / n,
        }


def statistics_from_samples(samples: np.ndarray, lam: float = BOX_COX_LAMBDA) -> dict[str, np.ndarray]:
    """Frame-format statistics layers of a stack of samples.

    samples: (N, H, W, C) float32 radiance, one image per sample. Returns the `layers()` dict.
    """
    stats = SampleStatistics.empty(*samples.shape[1:4])
    for sample in samples:
        stats.add(sample, lam)
    return stats.layers()
