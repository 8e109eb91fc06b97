"""Image error metrics shared by the demo, training and the benchmark: relL2 (full and trimmed), 1-SSIM,
FLIP and a temporal-stability relL2.

relL2 is the relative MSE of Rousselle et al. 2011 as the Choi et al. 2024 code computes it: the
mean over pixels and channels of (x - r)^2 / (m^2 + 0.01), where m is the mean of the reference's
three channels at the pixel. `rel_l2(..., trim=0.001)` drops the highest 0.1% of per-pixel errors
first, the usual convention that keeps a few aliased emitter-edge pixels from dominating.
"""

from __future__ import annotations

import numpy as np

from service.preview import tonemap

REL_L2_EPS = 0.01  # Rousselle 2011 / Choi 2024 code: denominator offset, radiance^2 units
TRIM_FRACTION = 0.001  # fraction of worst pixels dropped by the trimmed relL2


def rel_l2_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel relative squared error, averaged over channels.

    image, reference: (H, W, 3) float32 linear radiance. Returns (H, W) float64.
    """
    x = image.astype(np.float64)
    r = reference.astype(np.float64)
    m = r.mean(axis=-1, keepdims=True)
    return ((x - r) ** 2 / (m * m + REL_L2_EPS)).mean(axis=-1)


def rel_l2(image: np.ndarray, reference: np.ndarray, *, trim: float = 0.0) -> float:
    """Mean relL2 of `image` against `reference` ((H, W, 3) float32 linear radiance).

    trim: fraction in [0, 1) of the highest per-pixel errors dropped before averaging.
    """
    return trimmed_mean(rel_l2_map(image, reference), trim)


def trimmed_mean(errors: np.ndarray, trim: float) -> float:
    """Mean of `errors` (any shape, e.g. a `rel_l2_map` or its masked pixels) without the highest `trim`
    fraction in [0, 1) of them; NaN when `errors` is empty."""
    if not 0.0 <= trim < 1.0:
        raise ValueError(f"trim must be in [0, 1), got {trim}")
    errors = np.ravel(errors)
    if errors.size == 0:
        return float("nan")
    if trim > 0.0:
        keep = errors.size - int(np.floor(errors.size * trim))
        errors = np.partition(errors, keep - 1)[:keep]
    return float(errors.mean())


# --- 1-SSIM on tone-mapped images (Wang et al. 2004) --------------------------------------------------

SSIM_SIGMA = 1.5  # Wang 2004 sec. III-C: 11x11 circular-symmetric Gaussian window, standard deviation 1.5 px
SSIM_RADIUS = 5  # window half-width, pixels (11 taps)
SSIM_K1, SSIM_K2 = 0.01, 0.03  # Wang 2004 eq. 6-7 constants, for a dynamic range L = 1


def _gaussian_blur(x: np.ndarray) -> np.ndarray:
    """Separable SSIM Gaussian window over axes 0 and 1 of x (H, W, C) float64, reflect-padded at borders."""
    taps = np.exp(-0.5 * (np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1) / SSIM_SIGMA) ** 2)
    taps /= taps.sum()
    r = SSIM_RADIUS
    for axis in (0, 1):
        n = x.shape[axis]
        if n == 1:
            continue
        # Reflect (mirror without repeating the edge), periodically extended for axes shorter than the window.
        idx = np.arange(-r, n + r)
        period = 2 * (n - 1)
        idx = np.abs((idx + period) % period)
        idx = np.where(idx >= n, period - idx, idx)
        padded = np.take(x, idx, axis=axis)
        out = np.zeros_like(x)
        for k, weight in enumerate(taps):
            out += weight * np.take(padded, np.arange(k, k + n), axis=axis)
        x = out
    return x


def ssim_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (Wang 2004 eq. 13) of two display images.

    image, reference: (H, W, C) float in [0, 1] (display-referred, e.g. tone-mapped sRGB).
    Returns (H, W, C) float64; 1 where the images agree.
    """
    x = image.astype(np.float64)
    y = reference.astype(np.float64)
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    mx, my = _gaussian_blur(x), _gaussian_blur(y)
    vx = _gaussian_blur(x * x) - mx * mx
    vy = _gaussian_blur(y * y) - my * my
    cov = _gaussian_blur(x * y) - mx * my
    return ((2 * mx * my + c1) * (2 * cov + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def _display(color: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear radiance -> (H, W, 3) float64 in [0, 1]: service.preview.tonemap (x / (1 + x), sRGB,
    8-bit), the image a viewer of the demo sees."""
    return tonemap(color).astype(np.float64) / 255.0


def dssim(image: np.ndarray, reference: np.ndarray) -> float:
    """1 - mean SSIM of the tone-mapped images (Gaussian window, Wang 2004), over pixels and channels.

    image, reference: (H, W, 3) float32 linear HDR radiance. 0 for identical images, up to 2.
    """
    return float(1.0 - ssim_map(_display(image), _display(reference)).mean())


# --- FLIP (Andersson et al. 2020/2021) ----------------------------------------------------------------


def flip_error(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean HDR-FLIP error (flip-evaluator, default 67 pixels per degree) in [0, 1]; 0 for identical images.

    image, reference: (H, W, 3) float32 linear HDR radiance; negative and non-finite values count as 0
    (HDR-FLIP needs non-negative input). A reference with no positive value has no exposure range for
    HDR-FLIP; then the tone-mapped images (service.preview.tonemap) are compared with LDR-FLIP.
    Needs the `bench` extra (flip-evaluator), imported here only.
    """
    import flip_evaluator

    test = np.nan_to_num(np.maximum(image, 0.0), nan=0.0, posinf=0.0).astype(np.float32)
    ref = np.nan_to_num(np.maximum(reference, 0.0), nan=0.0, posinf=0.0).astype(np.float32)
    if np.any(ref > 0):
        args = (ref, test, "HDR")
    else:
        args = (_display(ref).astype(np.float32), _display(test).astype(np.float32), "LDR")
    try:
        _, mean, _ = flip_evaluator.evaluate(*args, applyMagma=False)
    except SystemExit as err:  # flip-evaluator exits the process on input it rejects
        raise ValueError(f"flip-evaluator rejected the input (exit status {err.code})") from None
    return float(mean)


# --- temporal stability -------------------------------------------------------------------------------


def temporal_rel_l2(prev_image: np.ndarray, image: np.ndarray, prev_reference: np.ndarray,
                    reference: np.ndarray) -> float:
    """relL2 of the frame-to-frame change of the output against that of the reference.

    All four: (H, W, 3) float32 linear radiance of frames t-1 and t. The mean over pixels and channels
    of ((x_t - x_{t-1}) - (r_t - r_{t-1}))^2 / (m^2 + 0.01), m the mean of r_t's channels: the relL2
    normalisation of `rel_l2_map` applied to the differences, normalised by the radiance (normalising
    by the reference's change would blow up on static pixels). 0 when the output changes exactly as
    the reference does (a static bias included), large for flicker.
    """
    # (x_t - x_{t-1}) - (r_t - r_{t-1}) = (x_t - x_{t-1} + r_{t-1}) - r_t: rel_l2_map of that image.
    moved = image.astype(np.float64) - prev_image + prev_reference
    return float(rel_l2_map(moved, reference).mean())
