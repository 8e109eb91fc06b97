"""Weighted local linear regression: the one solver behind cross-regression, BMFR and FLR.

- `solve`: many small ridge-regularised normal equations at once.
- `block`: block-wise regression (Choi et al. 2024, eqs. 3-5), `block_regression`, its numba kernels and
  their numpy twins (`reference=True`).
- `box`: the same for flat pair weights, from shared box sums (`box_regression`).
- `planes`: the channel-first (C, H, W) layout the kernels stream along x, and standardisation.

The outlier clamps that run before a regression are a stage of their own (`service.stages.outliers`).
Every fast numba kernel has a plain-numpy `*_reference` twin with the same signature; tests hold them
together.
"""
