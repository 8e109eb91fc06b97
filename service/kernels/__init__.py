"""JIT plumbing the numba stages share, not stages themselves: explicit SIMD vectors and aligned arrays
(`simd`), vectorisable fills (`fill`), the split of a frame's rows over threads (`parallel`) and clipped
window geometry (`window`)."""
