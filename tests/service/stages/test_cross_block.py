import numba
import numpy as np
import pytest

from service.kernels.simd import HALF, LANES
from service.regression.block import block_regression
from service.regression.planes import from_planes
from service.regression.solve import RIDGE_ABSOLUTE, RIDGE_RELATIVE, cholesky_ridge_solve
from service.regression.terms import BlockParams
from service.stages.cross_block import (
    BUFFER_A,
    FEATURES,
    MASK,
    _cholesky_solve,
    band_gap,
    centre_bands,
    pack_cross_reference,
    regress_packed,
    regress_sums,
)
from service.stages.cross_regression import buffer_terms, linear_to_log, pixel_variance_reference

PARITY_RTOL = 2e-4  # SIMD kernel (other summation order, float32 moments) vs the numpy reference, float32


def _buffers(rng: np.random.Generator, height: int, width: int) -> dict[str, np.ndarray]:
    """Two noisy log-colour buffers of one smooth signal with an edge, and G-buffers, as planes."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    signal = 1.0 + 0.5 * np.sin(0.3 * x + 0.2 * y) + (x > width / 2)
    albedo = rng.random((3, height, width), dtype=np.float32)
    normal = rng.standard_normal((3, height, width)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=0, keepdims=True)
    out = {"albedo": albedo, "normal": normal}
    for name in ("a", "b"):
        radiance = signal * albedo * rng.lognormal(0.0, 0.5, (3, height, width)).astype(np.float32)
        out[name] = linear_to_log(radiance)
        out["var_" + name] = pixel_variance_reference(out[name])
    return out


def _reference(inputs: dict[str, np.ndarray], params: BlockParams) -> tuple[np.ndarray, np.ndarray]:
    albedo, normal = inputs["albedo"], inputs["normal"]
    terms_a = buffer_terms(inputs["a"], inputs["var_a"], albedo, normal)
    terms_b = buffer_terms(inputs["b"], inputs["var_b"], albedo, normal)
    return (block_regression(terms_a, inputs["b"], params, reference=True),
            block_regression(terms_b, inputs["a"], params, reference=True))  # fmt: skip


def _run(inputs: dict[str, np.ndarray], params: BlockParams) -> tuple[np.ndarray, np.ndarray]:
    planes = pack_cross_reference(inputs["a"], inputs["var_a"], inputs["b"], inputs["var_b"],
                                  from_planes(inputs["albedo"]), from_planes(inputs["normal"]), params)  # fmt: skip
    return regress_packed(planes, inputs["a"].shape[2], params)


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (17, 31), (29, 22), (9, 4 * LANES * 2 + 7)])  # last: 3 lane groups
@pytest.mark.parametrize(
    "params",
    [BlockParams(), BlockParams(radius=5, sparsity=3, sigma_position=4.0), BlockParams(radius=2, sparsity=1)],
    ids=["paper", "gaussian", "dense"],
)
def test_regress_packed_matches_the_numpy_reference(size, params):
    inputs = _buffers(np.random.default_rng(3), *size)
    for out, ref in zip(_run(inputs, params), _reference(inputs, params), strict=True):
        assert out.shape == (3, *size) and out.dtype == np.float32
        np.testing.assert_allclose(out, ref, rtol=PARITY_RTOL, atol=PARITY_RTOL * np.abs(ref).max())


SUMS_PARAMS = [BlockParams(), BlockParams(radius=5, sparsity=3), BlockParams(radius=2, sparsity=1),
               BlockParams(radius=3, sparsity=4)]  # fmt: skip


def _packed(inputs: dict[str, np.ndarray], params: BlockParams) -> np.ndarray:
    return pack_cross_reference(inputs["a"], inputs["var_a"], inputs["b"], inputs["var_b"],
                                from_planes(inputs["albedo"]), from_planes(inputs["normal"]), params)  # fmt: skip


@pytest.mark.parametrize("params", SUMS_PARAMS, ids=["paper", "sparsity3", "dense", "narrow"])
@pytest.mark.parametrize("tasks", [1, 3])
def test_regress_sums_sets_every_sum_itself(params, tasks, monkeypatch):
    """The kernel zeroes the sums it returns (each chunk the rows it reaches first, each lane group its lanes,
    as it starts): the same sums come back when the memory handed out for them is full of NaN. Several
    chunks, bands and lane groups."""
    inputs = _buffers(np.random.default_rng(8), 90, 4 * LANES * 3 + 7)
    planes = _packed(inputs, params)
    clean = regress_sums(planes, inputs["a"].shape[2], params, tasks)
    empty = np.empty

    def nan_empty(*args, **kwargs):
        out = empty(*args, **kwargs)
        out.fill(np.nan)
        return out

    monkeypatch.setattr(np, "empty", nan_empty)
    dirty = regress_sums(planes, inputs["a"].shape[2], params, tasks)
    monkeypatch.undo()
    for got, want in zip(dirty, clean, strict=True):
        np.testing.assert_array_equal(got, want)


def test_regress_sums_rows_start_on_cache_lines():
    """Each row of the sums is a whole number of vectors from a 64-byte boundary (the strip adds whole
    vectors at multiples of LANES lanes)."""
    inputs = _buffers(np.random.default_rng(10), 21, 37)
    for sums in regress_sums(_packed(inputs, BlockParams()), 37, BlockParams()):
        assert sums.ctypes.data % 64 == 0 and sums.shape[-1] % LANES == 0


@pytest.mark.parametrize("params", SUMS_PARAMS, ids=["paper", "sparsity3", "dense", "narrow"])
def test_regress_sums_do_not_depend_on_the_bands(params):
    """1 to 5 bands (and their gaps, run after them) give the same sums up to float32 summation order."""
    inputs = _buffers(np.random.default_rng(9), 150, 2 * LANES * 3 + 5)
    planes = _packed(inputs, params)
    one = regress_sums(planes, inputs["a"].shape[2], params, 1)
    for tasks in (2, 3, 5):
        for got, want in zip(regress_sums(planes, inputs["a"].shape[2], params, tasks), one, strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


@pytest.mark.parametrize("params", SUMS_PARAMS, ids=["paper", "sparsity3", "dense", "narrow"])
@pytest.mark.parametrize("centre_rows", [1, 2, 9, 10, 37, 180])
@pytest.mark.parametrize("tasks", [1, 2, 3, 16])
def test_centre_bands_keep_their_windows_apart(params, centre_rows, tasks):
    """Bands tile the centre rows in order with gaps of band_gap rows; no two bands' windows, nor two gaps',
    share a pixel row; as many bands as tasks when the rows allow."""
    s, r, gap = params.sparsity, params.radius, band_gap(params)
    bands = centre_bands(centre_rows, params, tasks)
    assert bands.dtype == np.int64 and bands[0, 0] == 0 and bands[-1, 1] == centre_rows
    assert 1 <= len(bands) <= tasks and np.all(bands[:, 1] > bands[:, 0])
    np.testing.assert_array_equal(bands[1:, 0] - bands[:-1, 1], gap)
    assert np.all(s * bands[1:, 0] - r > s * (bands[:-1, 1] - 1) + r)  # bands: no shared window row
    assert np.all(s * bands[1:-1, 1] - r > s * (bands[1:-1, 0] - 1) + r)  # gaps: none either
    if len(bands) < tasks:
        assert centre_rows < (len(bands) + 1) * (2 * gap + 1) - gap  # one more band would be shorter than a gap
    assert np.ptp(bands[:, 1] - bands[:, 0]) <= 1


def test_pilot_a_is_fitted_to_buffer_b():
    """Buffer B constant: pilot_a (A's features, B's colours) is that constant; pilot_b is not."""
    inputs = _buffers(np.random.default_rng(4), 20, 24)
    inputs["b"] = np.full_like(inputs["b"], 0.7)
    inputs["var_b"] = np.zeros_like(inputs["var_b"])
    pilot_a, pilot_b = _run(inputs, BlockParams())
    np.testing.assert_allclose(pilot_a, 0.7, rtol=1e-5)
    assert np.abs(pilot_b - 0.7).max() > 0.1


def test_constant_g_buffers_and_black_frames_stay_finite():
    """Constant albedo and normal make the normal equations singular: the ridge keeps the result finite."""
    zeros = np.zeros((3, 13, 18), np.float32)
    inputs = {"a": zeros, "b": zeros, "var_a": zeros[0], "var_b": zeros[0], "albedo": zeros + 0.5, "normal": zeros}
    for pilot in _run(inputs, BlockParams()):
        np.testing.assert_array_equal(pilot, 0.0)


def test_pack_cross_reference_is_the_phase_split():
    """Pixel x = 3 q + phase lands at lane q + pad of its phase plane; the mask marks the frame."""
    inputs = _buffers(np.random.default_rng(6), 2, 7)
    args = (inputs["a"], inputs["var_a"], inputs["b"], inputs["var_b"], from_planes(inputs["albedo"]),
            from_planes(inputs["normal"]), BlockParams(radius=5, sparsity=3))  # fmt: skip
    packed = pack_cross_reference(*args)
    np.testing.assert_array_equal(packed[1, BUFFER_A, :, 2:5], inputs["a"][0][:, [1, 4, 7 - 1]] * [1, 1, 0])
    np.testing.assert_array_equal(packed[2, MASK, 0, :5], [0, 0, 1, 1, 0])  # x = 2, 5; nothing at 8


@numba.njit
def _both_solvers(gram, rhs, out_vec, out_scalar):
    a, b = gram.copy().reshape(1, FEATURES, FEATURES, LANES), rhs.copy().reshape(1, FEATURES, LANES)
    for h in (0, HALF):
        _cholesky_solve(a, b, 0, RIDGE_RELATIVE, RIDGE_ABSOLUTE, h)
    out_vec[:] = b[0]
    a, b = gram.copy(), rhs.copy().reshape(FEATURES, 1, LANES)
    cholesky_ridge_solve(a, b, FEATURES, 1, RIDGE_RELATIVE, RIDGE_ABSOLUTE, True, np.empty(0), LANES)
    out_scalar[:] = b[:, 0]


def test_vector_cholesky_is_the_scalar_solver():
    """Random, rank-deficient (constant features) and all-zero (no weight) systems, one per lane."""
    rng = np.random.default_rng(7)
    gram, rhs = np.zeros((FEATURES, FEATURES, LANES)), np.zeros((FEATURES, LANES))
    for lane in range(LANES - 1):
        x = rng.standard_normal((40, FEATURES))
        x[:, 0] = 1.0
        if lane % 3 == 1:
            x[:, 2:4] = 0.5  # constant features: singular without the ridge
        gram[:, :, lane], rhs[:, lane] = x.T @ x, x.T @ rng.standard_normal(40)
    out_vec, out_scalar = np.empty_like(rhs), np.empty_like(rhs)
    _both_solvers(gram, rhs, out_vec, out_scalar)
    assert np.isfinite(out_vec).all() and not out_vec[:, -1].any()  # no weight: beta = 0
    np.testing.assert_allclose(out_vec, out_scalar, rtol=1e-12, atol=1e-12)
