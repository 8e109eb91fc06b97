import platform

import numba
import numpy as np
import pytest

from service.kernels.simd import (
    EXP_NEG_LIMIT,
    HALF,
    LANES,
    aligned_empty,
    exp_neg,
    floor,
    jit_aligned_empty,
    load,
    load_phase,
    narrow,
    prefetch,
    splat,
    splat_d,
    sqrt,
    store,
    store_phases,
    vmax,
    vmin,
    widen,
)
from service.regression.block import _exp_neg

EXP_RTOL = 5e-7  # exp_neg on [0, 86]: the rounding of ln 2 times m grows the error with x (4.2e-7 at 85)


@numba.njit(fastmath=True)
def _lanewise(x, y, out):
    for i in range(0, x.shape[1], LANES):
        a, b = load(x, (0, i)), load(y, (0, i))
        store(out, (0, i), a + b)
        store(out, (1, i), a - 2.0 * b)
        store(out, (2, i), (a * b) / (b + np.float32(1.0)))
        store(out, (3, i), vmax(a, b))
        store(out, (4, i), floor(a))
        acc = splat(np.float32(0.5))
        acc += a
        acc *= b
        store(out, (5, i), acc)
        store(out, (6, i), exp_neg(b))
        store(out, (7, i), vmin(a, b))


@numba.njit(fastmath=True)
def _exp_neg_scalar(x, out):
    for i in range(x.shape[0]):
        out[i] = _exp_neg(x[i])


def test_vec_arithmetic_is_lane_wise_float32():
    rng = np.random.default_rng(0)
    x = rng.uniform(-50.0, 50.0, (1, 4 * LANES)).astype(np.float32)
    y = rng.uniform(0.0, 80.0, (1, 4 * LANES)).astype(np.float32)
    out = np.zeros((8, 4 * LANES), np.float32)
    _lanewise(x, y, out)
    a, b = x[0], y[0]
    expected = [a + b, a - 2 * b, a * b / (b + 1), np.maximum(a, b), np.floor(a), (0.5 + a) * b]
    for got, want in zip(out[:6], expected, strict=True):
        np.testing.assert_allclose(got, want.astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(out[6], np.exp(-b.astype(np.float64)), rtol=EXP_RTOL, atol=0.0)
    np.testing.assert_array_equal(out[7], np.minimum(a, b))


def test_exp_neg_is_the_scalar_polynomial_bit_for_bit():
    x = np.concatenate([[0.0, 1e-8, 0.5, 86.0, 87.0, 88.0, 1e30, np.inf], np.linspace(0, 90, 8 * LANES - 8)])
    x = x.astype(np.float32)
    vector, scalar = np.zeros((8, x.size), np.float32), np.zeros(x.size, np.float32)
    _lanewise(np.zeros((1, x.size), np.float32), x[None], vector)
    _exp_neg_scalar(x, scalar)
    np.testing.assert_array_equal(vector[6], scalar)
    assert (vector[6] > 0).all() and vector[6].max() == 1.0
    clamped = vector[6][4:8]  # x = 87, 88, 1e30, inf: exp(-EXP_NEG_LIMIT), a normal float32
    assert (clamped == vector[6][3]).all() and clamped[0] >= np.finfo(np.float32).tiny
    np.testing.assert_allclose(clamped, np.exp(-EXP_NEG_LIMIT), rtol=EXP_RTOL)


def test_load_and_store_touch_exactly_one_vec():
    src = np.arange(3 * 2 * 40, dtype=np.float32).reshape(3, 2, 40)
    dst = np.zeros_like(src)

    @numba.njit
    def copy(src, dst):
        store(dst, (2, 1, 5), load(src, (1, 0, 7)))

    copy(src, dst)
    np.testing.assert_array_equal(dst[2, 1, 5 : 5 + LANES], src[1, 0, 7 : 7 + LANES])
    dst[2, 1, 5 : 5 + LANES] = 0.0
    assert not dst.any()


@numba.njit
def _phases(src, out):
    store(out, (0, 0), load_phase(src, (1, 3), 4, 0))
    store(out, (1, 0), load_phase(src, (1, 3), 4, 3))
    store(out, (2, 0), load_phase(src, (0, 5), 12, 7))
    store(out, (3, 0), load_phase(src, (1, 2), 1, 0))


def test_load_phase_takes_every_stride_th_value():
    for dtype, lanes in ((np.float32, LANES), (np.float64, HALF)):
        src = np.arange(2 * (12 * lanes + 5), dtype=dtype).reshape(2, -1)  # (0, 5) on: 12 vectors, to the end
        out = np.zeros((4, lanes), dtype)
        _phases(src, out)
        q = np.arange(lanes)
        expected = [src[1, 3 + 4 * q], src[1, 6 + 4 * q], src[0, 12 + 12 * q], src[1, 2 + q]]
        np.testing.assert_array_equal(out, expected)


def test_load_phase_needs_a_literal_phase_below_the_stride():
    @numba.njit
    def bad(src, out):
        store(out, (0,), load_phase(src, (0,), 4, 4))

    with pytest.raises(numba.TypingError, match="simd.load_phase: needs literal ints 0 <= phase < stride"):
        bad(np.zeros(8 * LANES, np.float32), np.zeros(LANES, np.float32))


@numba.njit
def _round_trip(src, x, out):
    store_phases(out, (1, x), load_phase(src, (x,), 4, 0), load_phase(src, (x,), 4, 1), load_phase(src, (x,), 4, 2),
                 load_phase(src, (x,), 4, 3))  # fmt: skip


def test_store_phases_undoes_load_phase_and_writes_only_its_values():
    for dtype, lanes in ((np.float32, LANES), (np.float64, HALF)):
        src = np.arange(4 * lanes + 3, dtype=dtype) + 1
        out = np.zeros((2, 4 * lanes + 3), dtype)
        _round_trip(src, 3, out)
        np.testing.assert_array_equal(out[1, 3:], src[3:])
        assert not out[0].any() and not out[1, :3].any()


@numba.njit(fastmath=True)
def _double_ops(x, y, out, back):
    for h in (0, HALF):
        a, b = load(x, (h,)), load(y, (h,))
        store(out, (0, h), sqrt(a) + b / (a + 1.0))
        store(out, (1, h), vmax(a, b) * splat_d(2.0))
    v = load(back, (0, 0))
    store(back, (1, 0), narrow(widen(v, 1), widen(v, 0)))  # halves swapped


def test_double_vectors_widen_and_narrow():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0.0, 9.0, LANES), rng.uniform(-3.0, 3.0, LANES)
    out = np.zeros((2, LANES))
    back = np.zeros((2, LANES), np.float32)
    back[0] = rng.standard_normal(LANES)
    _double_ops(x, y, out, back)
    np.testing.assert_allclose(out[0], np.sqrt(x) + y / (x + 1.0), rtol=1e-14)
    np.testing.assert_array_equal(out[1], np.maximum(x, y) * 2.0)
    np.testing.assert_array_equal(back[1], np.concatenate([back[0, HALF:], back[0, :HALF]]))


def test_prefetch_is_a_hint_that_changes_no_value():
    """The kernel's prefetch reads nothing into the program: the array and the result stay as they were, at
    any index (past the end included: a prefetch does not fault); on x86 it compiles to a prefetch."""
    values = np.arange(4 * 40, dtype=np.float32).reshape(4, 40)

    @numba.njit
    def summed_after_prefetch(values, row):
        prefetch(values, (row, 0))
        prefetch(values, (row, 3 * LANES))
        return values.sum()

    before = values.copy()
    assert summed_after_prefetch(values, 1) == before.sum()
    assert summed_after_prefetch(values, 3) == before.sum()
    np.testing.assert_array_equal(values, before)
    if platform.machine() in ("x86_64", "AMD64"):
        assembly = next(iter(summed_after_prefetch.inspect_asm().values()))
        assert "prefetcht0" in assembly


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(1,), (3, 5), (2, 4, 3, 7, 48)])
def test_aligned_empty_starts_on_a_cache_line(shape, dtype):
    for _ in range(8):  # numpy's allocations land on different 16-byte offsets
        a = aligned_empty(shape, dtype)
        assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable
        assert a.ctypes.data % 64 == 0
        a[...] = 1.0  # the whole array is owned memory
        assert a.sum() == a.size


@numba.njit
def _aligned_in_numba(rows):
    """Offsets from a cache line of jit_aligned_empty arrays (float32 and float64, several shapes), and
    whether each holds what was written (its shape, strides and ownership right)."""
    offsets = np.empty((rows, 3), np.int64)
    held = True
    for i in range(rows):
        a = jit_aligned_empty((i + 1, 3, LANES), np.float32)
        b = jit_aligned_empty((2, i + 1), np.float64)
        c = jit_aligned_empty((i + 5,), np.float32)
        a[:] = np.float32(i)
        b[:] = 0.5
        c[:] = 2.0
        held &= a.sum() == i * a.size and b.sum() == 0.5 * b.size and c.sum() == 2.0 * c.size
        held &= a.strides == (3 * LANES * 4, LANES * 4, 4) and b.strides == ((i + 1) * 8, 8)
        offsets[i] = a.ctypes.data % 64, b.ctypes.data % 64, c.ctypes.data % 64
    return offsets, held


def test_jit_aligned_empty_starts_on_a_cache_line_in_numba_code():
    """numba's own np.empty is 32-byte aligned (half the kernel's scratch arrays spanned two cache lines per
    vector); jit_aligned_empty gives whole C-contiguous arrays from a 64-byte boundary."""
    offsets, held = _aligned_in_numba(40)
    assert held
    np.testing.assert_array_equal(offsets, 0)


@numba.njit
def _aligned_returned(rows):
    return jit_aligned_empty((rows, LANES), np.float32)


def test_jit_aligned_empty_arrays_are_freed_once():
    """Each array the intrinsic makes holds one reference: freed when the kernel drops it, and one that
    reaches Python is owned by its numpy array and freed with it (numba's allocation counters, switched on
    here: they are off unless NUMBA_NRT_STATS is set before numba starts)."""
    from numba.core.runtime import _nrt_python, rtsys

    _nrt_python.memsys_enable_stats()
    _aligned_in_numba(1), _aligned_returned(1)  # compiled before counting
    before = rtsys.get_allocation_stats()
    _aligned_in_numba(40)
    after = rtsys.get_allocation_stats()
    assert after.mi_alloc - before.mi_alloc == 3 * 40 + 1  # + the offsets
    assert after.mi_free - before.mi_free == 3 * 40 + 1  # the offsets are freed when the tuple goes
    returned = _aligned_returned(5)
    returned[:] = 3.0
    assert returned.ctypes.data % 64 == 0 and returned.sum() == 3.0 * returned.size
    kept = rtsys.get_allocation_stats()
    del returned
    assert rtsys.get_allocation_stats().mi_free - kept.mi_free == 1


def test_jit_aligned_empty_rejects_other_dtypes_and_shapes():
    @numba.njit
    def of_ints():
        return jit_aligned_empty((3,), np.int32)

    @numba.njit
    def of_floats():
        return jit_aligned_empty((3.0,), np.float32)

    for compiled in (of_ints, of_floats):
        with pytest.raises(numba.core.errors.TypingError, match="jit_aligned_empty"):
            compiled()
