"""Explicit SIMD vectors for numba kernels: `Vec` (LANES float32) and `VecD` (LANES / 2 float64), each
one LLVM vector value.

numba's auto-vectoriser only vectorises innermost loops, so a kernel whose accumulators must stay in
registers across an inner loop (the window offsets of a regression) is left scalar or spills every
accumulator to memory on every step, and a loop over a literal 16 lanes is unrolled into scalar code.
With these types a kernel writes the vector code itself: a local variable is an LLVM vector, which the
register allocator keeps in a SIMD register. LANES = 16 float32 (or 8 float64) is one AVX-512
register; on narrower hardware LLVM splits each operation (two AVX2 ops, four NEON ops), so the same
kernel is correct everywhere.

In numba code (lane-wise, fast-math: fused multiply-adds and reassociation allowed):
    v = load(array, (i, j, k))    # consecutive values along the last axis from array[i, j, k]: a Vec
                                  # from a float32 array, a VecD from a float64 one (C-contiguous,
    store(array, (i, j, k), v)    # indices unchecked), and the reverse
    v = splat(x)                  # Vec with every lane float32(x); splat_d(x): VecD, float64(x)
    v = load_phase(array, (i, j), n, p)  # every n-th value from array[i, j + p] on (n, p literal ints,
                                  # p < n): lane q is array[i, j + n q + p]; one wide load and a shuffle
    store_phases(array, (i, j), v0, v1, v2, v3)  # the reverse at n = 4: array[i, j + 4 q + p] = v_p[q]
    phase_blocks(width, sparsity)  # the pixels of a row that those two move as whole blocks
    prefetch(array, (i, j, k))    # ask for the cache line of array[i, j, k] in L1 (no effect on values)
    v + w, v - w, v * w, v / w    # same-type vectors; either side may also be a Python/numpy number
    vmax(v, w), vmin(v, w), floor(v), sqrt(v), exp_neg(v)
    d = widen(v, half)            # VecD of lanes half * LANES/2 ... of the Vec v
    v = narrow(lo, hi)            # Vec of two VecD halves, rounded to float32
`exp_neg` is the vector twin of `regression.block._exp_neg` (the same operations, the same values; both
evaluate `exp_poly`, which takes a float32 or a Vec).

Also here, for numpy code: `aligned_empty`, arrays that start on a vector (and cache line) boundary, and
`jit_aligned_empty`, the same in numba code. For
scalar numba code: `bits_to_float32` and `float32_to_bits`, the bit casts with which the
exp and log polynomials of the stages build and split float32 exponents (they vectorise, unlike calls
to the C library's expf or frexpf).
"""

from __future__ import annotations

import operator

import llvmlite.ir as ir
import numba
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model

LANES = 16  # float32 lanes of one Vec: one AVX-512 register; a VecD holds LANES // 2 float64
HALF = LANES // 2

# exp(-x) (`exp_neg` and its scalar twin `regression.block._exp_neg`): x = m ln2 - g, |g| <= ln2 / 2, and
# e^g by a degree-5 polynomial (coefficients of g^0 ... g^5) with e^0 = 1 exactly and the least maximum
# relative error on [-ln2/2, ln2/2] for that (Lawson's iteration: 9.2e-8). x is clipped to EXP_NEG_LIMIT,
# so that 2^-m e^g stays a normal float32 (m <= 124) and takes its exponent by integer subtraction.
EXP_POLY = (1.0, 0.9999997072462664, 0.4999914970284134, 0.16667636167565678, 0.041897906037271136,
            0.008290304318230728)  # fmt: skip
EXP_NEG_LIMIT = 86.0
LOG2E, LN2 = 1.4426950408889634, 0.6931471805599453

_FAST = ("fast",)
_INT32 = ir.IntType(32)
_INTS = ir.VectorType(_INT32, LANES)


class VecType(types.Type):
    """numba type of a SIMD vector: `count` values of `dtype` (types.float32 or types.float64)."""

    def __init__(self, dtype: types.Float, count: int) -> None:
        self.dtype, self.count = dtype, count
        super().__init__(name=f"Vec{count}x{dtype}")

    @property
    def llvm(self) -> ir.VectorType:
        return ir.VectorType(ir.FloatType() if self.dtype == types.float32 else ir.DoubleType(), self.count)

    @property
    def suffix(self) -> str:
        """LLVM intrinsic name suffix, e.g. v16f32."""
        return f"v{self.count}f{self.dtype.bitwidth}"


vec = VecType(types.float32, LANES)
vec_d = VecType(types.float64, HALF)
_BY_DTYPE = {types.float32: vec, types.float64: vec_d}


@register_model(VecType)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, fe_type.llvm)


def _vector_of(array) -> VecType:
    if not (isinstance(array, types.Array) and array.dtype in _BY_DTYPE and array.layout == "C"):
        raise numba.TypingError(f"simd: needs a C-contiguous float32 or float64 array, got {array}")
    return _BY_DTYPE[array.dtype]


def _pointer(context, builder, aryty, ary, index, indices, vector: VecType):
    """LLVM pointer to array[indices], as a pointer to a whole vector."""
    array = context.make_array(aryty)(context, builder, ary)
    items = cgutils.unpack_tuple(builder, index, len(indices))
    items = [context.cast(builder, item, ty, types.intp) for item, ty in zip(items, indices, strict=True)]
    ptr = cgutils.get_item_pointer(context, builder, aryty, array, items)
    return builder.bitcast(ptr, vector.llvm.as_pointer())


def _check_index(array, index) -> None:
    if not (isinstance(index, types.BaseTuple) and len(index) == array.ndim):
        raise numba.TypingError(f"simd: needs a tuple of {array.ndim} indices, got {index}")


@intrinsic
def load(typingctx, array, index):
    """The vector at array[index] and the values after it along the last axis (unaligned load)."""
    vector = _vector_of(array)
    _check_index(array, index)

    def codegen(context, builder, sig, args):
        return builder.load(_pointer(context, builder, array, args[0], args[1], index.types, vector), align=4)

    return vector(array, index), codegen


@intrinsic
def store(typingctx, array, index, value):
    """Write a vector to array[index] and the places after it along the last axis."""
    vector = _vector_of(array)
    _check_index(array, index)
    if value != vector:
        raise numba.TypingError(f"simd: cannot store {value} into {array}")

    def codegen(context, builder, sig, args):
        builder.store(args[2], _pointer(context, builder, array, args[0], args[1], index.types, vector), align=4)
        return context.get_dummy_value()

    return types.void(array, index, vector), codegen


@intrinsic
def load_phase(typingctx, array, index, stride, phase):
    """The vector of every stride-th value along the last axis from `phase` places after array[index] on: lane q
    is the value stride * q + phase places on (stride and phase literal ints, 0 <= phase < stride). One wide
    load of stride vectors and a shuffle: the calls for the phases of one index share the load, and split a
    row into phases, or de-interleave channels, without gathers."""
    vector = _vector_of(array)
    _check_index(array, index)
    literal = all(isinstance(x, types.IntegerLiteral) for x in (stride, phase))
    if not literal or not 0 <= phase.literal_value < stride.literal_value:
        raise numba.TypingError(f"simd.load_phase: needs literal ints 0 <= phase < stride, got {phase}, {stride}")
    n, first, count = stride.literal_value, phase.literal_value, vector.count
    wide = ir.VectorType(vector.llvm.element, n * count)

    def codegen(context, builder, sig, args):
        ptr = _pointer(context, builder, array, args[0], args[1], index.types, vector)
        values = builder.load(builder.bitcast(ptr, wide.as_pointer()), align=4)
        mask = ir.Constant(ir.VectorType(_INT32, count), list(range(first, n * count, n)))
        return builder.shuffle_vector(values, ir.Constant(wide, ir.Undefined), mask)

    return vector(array, index, stride, phase), codegen


@intrinsic
def store_phases(typingctx, array, index, v0, v1, v2, v3):
    """The inverse of `load_phase` at stride 4: lane q of v_p to array[index] + 4 q + p, for the 4 LANES
    values from array[index] on (four vectors of the array's type). Two shuffles and one wide store: phase
    planes back to pixels without scattered scalar stores."""
    vector = _vector_of(array)
    _check_index(array, index)
    if any(v != vector for v in (v0, v1, v2, v3)):
        raise numba.TypingError(f"simd.store_phases: needs four {vector} vectors")
    count = vector.count
    halves = ir.Constant(ir.VectorType(_INT32, 2 * count), list(range(2 * count)))  # concatenation
    # out[4 q + p] = v_p[q]: from (v0, v2) for even p, (v1, v3) for odd p, the second of each pair at + count
    order = [k for q in range(count) for k in (q, 2 * count + q, count + q, 3 * count + q)]
    wide = ir.VectorType(vector.llvm.element, 4 * count)

    def codegen(context, builder, sig, args):
        ptr = _pointer(context, builder, array, args[0], args[1], index.types, vector)
        even = builder.shuffle_vector(args[2], args[4], halves)
        odd = builder.shuffle_vector(args[3], args[5], halves)
        values = builder.shuffle_vector(even, odd, ir.Constant(ir.VectorType(_INT32, 4 * count), order))
        builder.store(values, builder.bitcast(ptr, wide.as_pointer()), align=4)
        return context.get_dummy_value()

    return types.void(array, index, v0, v1, v2, v3), codegen


@intrinsic
def prefetch(typingctx, array, index):
    """Hint that array[index] (C-contiguous float32 or float64) will be read soon: LLVM's prefetch for a read
    into all cache levels (x86 `prefetcht0`; nothing where the CPU has none). Indices unchecked, like
    `load`; a prefetch of an address outside the array does not fault."""
    vector = _vector_of(array)
    _check_index(array, index)
    byte_pointer = ir.IntType(8).as_pointer()
    signature = ir.FunctionType(ir.VoidType(), [byte_pointer, _INT32, _INT32, _INT32])

    def codegen(context, builder, sig, args):
        ptr = builder.bitcast(_pointer(context, builder, array, args[0], args[1], index.types, vector), byte_pointer)
        fn = cgutils.get_or_insert_function(builder.module, signature, "llvm.prefetch.p0i8")
        read, locality, data = (ir.Constant(_INT32, v) for v in (0, 3, 1))  # read, keep in all levels, data cache
        builder.call(fn, [ptr, read, locality, data])
        return context.get_dummy_value()

    return types.void(array, index), codegen


def aligned_empty(shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
    """Uninitialised C-contiguous array of `shape` whose first element lies on a 64-byte boundary (one
    AVX-512 vector, one cache line; numpy's own allocations are 16-byte aligned)."""
    itemsize = np.dtype(dtype).itemsize
    count = int(np.prod(shape))
    buffer = np.empty(count + 64 // itemsize, dtype)
    first = (-buffer.ctypes.data % 64) // itemsize
    return buffer[first : first + count].reshape(shape)


@intrinsic
def jit_aligned_empty(typingctx, shape, dtype):
    """`aligned_empty` in numba code: np.empty(shape, dtype), C-contiguous, its data on a 64-byte boundary
    (numba's own np.empty gives 32: a vector stored at an odd 32 bytes spans two cache lines). shape: a
    tuple of ints >= 0 (unchecked: for scratch of known size); dtype: np.float32 or np.float64. The shape
    stays the tuple's values, so that with constant trailing sizes the compiler folds the element offsets
    (a reshaped, aligned slice of a larger array computes them at run time)."""
    if not isinstance(shape, types.UniTuple) or not isinstance(shape.dtype, types.Integer):
        raise numba.core.errors.TypingError(f"jit_aligned_empty: shape must be a tuple of ints, got {shape}")
    element = dtype.dtype if isinstance(dtype, types.NumberClass) else None
    if element not in (types.float32, types.float64):
        raise numba.core.errors.TypingError(f"jit_aligned_empty: dtype must be np.float32 or np.float64, got {dtype}")
    result = types.Array(element, shape.count, "C")

    def codegen(context, builder, sig, args):
        intp = context.get_value_type(types.intp)
        sizes = cgutils.unpack_tuple(builder, args[0])
        shapes = [builder.sext(s, intp) if s.type.width < intp.width else s for s in sizes]
        itemsize = ir.Constant(intp, context.get_abi_sizeof(context.get_data_type(element)))
        strides = [itemsize]
        for size in reversed(shapes[1:]):
            strides.insert(0, builder.mul(strides[0], size))
        nbytes = builder.mul(strides[0], shapes[0])
        meminfo = context.nrt.meminfo_alloc_aligned(builder, nbytes, 64)
        array = context.make_array(result)(context, builder)
        data = builder.bitcast(context.nrt.meminfo_data(builder, meminfo), context.get_data_type(element).as_pointer())
        context.populate_array(array, data=data, shape=cgutils.pack_array(builder, shapes),
                               strides=cgutils.pack_array(builder, strides), itemsize=itemsize, meminfo=meminfo)
        return array._getvalue()  # a new reference, which the caller owns

    return result(shape, dtype), codegen


@numba.njit(inline="always")
def phase_blocks(width, sparsity):
    """Pixels at the start of a row of `width` that fill whole blocks of 4 LANES, which `load_phase` and
    `store_phases` split into and join from 4 phase vectors: sparsity 4 only (the paper's), 0 otherwise."""
    return width // (4 * LANES) * 4 * LANES if sparsity == 4 else 0


def _fill(builder, vector: VecType, value):
    """LLVM vector of `vector`'s type with every lane = value (already of its element type)."""
    one = builder.insert_element(ir.Constant(vector.llvm, ir.Undefined), value, ir.Constant(_INT32, 0))
    return builder.shuffle_vector(one, one, ir.Constant(ir.VectorType(_INT32, vector.count), [0] * vector.count))


def _splat_into(vector: VecType):
    def splat_intrinsic(typingctx, x):
        def codegen(context, builder, sig, args):
            return _fill(builder, vector, context.cast(builder, args[0], sig.args[0], vector.dtype))

        return vector(x), codegen

    return intrinsic(splat_intrinsic)


splat = _splat_into(vec)
splat_d = _splat_into(vec_d)


def _binary(name: str):
    @intrinsic
    def op(typingctx, a, b):
        def codegen(context, builder, sig, args):
            return getattr(builder, name)(args[0], args[1], flags=_FAST)

        return a(a, b), codegen

    return op


_add, _sub, _mul, _div = (_binary(name) for name in ("fadd", "fsub", "fmul", "fdiv"))


@intrinsic
def _broadcast(typingctx, like, x):
    """x (a number) as a vector of like's type."""

    def codegen(context, builder, sig, args):
        return _fill(builder, like, context.cast(builder, args[1], sig.args[1], like.dtype))

    return like(like, x), codegen


def _overload_operator(operation, op) -> None:
    @overload(operation)
    def impl(a, b):
        if isinstance(a, VecType) and a == b:
            return lambda a, b: op(a, b)
        if isinstance(a, VecType) and isinstance(b, (types.Float, types.Integer)):
            return lambda a, b: op(a, _broadcast(a, b))
        if isinstance(a, (types.Float, types.Integer)) and isinstance(b, VecType):
            return lambda a, b: op(_broadcast(b, a), b)
        return None


_IN_PLACE = {operator.add: operator.iadd, operator.sub: operator.isub, operator.mul: operator.imul,
             operator.truediv: operator.itruediv}  # fmt: skip
for _operation, _op in ((operator.add, _add), (operator.sub, _sub), (operator.mul, _mul), (operator.truediv, _div)):
    _overload_operator(_operation, _op)
    _overload_operator(_IN_PLACE[_operation], _op)


def _call_llvm(builder, name: str, vector: VecType, *args):
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vector.llvm, [vector.llvm] * len(args)), name)
    return builder.call(fn, args)


@intrinsic
def vmax(typingctx, a, b):
    """Lane-wise maximum of two vectors of one type."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.maxnum.{a.suffix}", a, args[0], args[1])

    return a(a, b), codegen


@intrinsic
def floor(typingctx, a):
    """Lane-wise floor."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.floor.{a.suffix}", a, args[0])

    return a(a), codegen


@intrinsic
def sqrt(typingctx, a):
    """Lane-wise square root."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.sqrt.{a.suffix}", a, args[0])

    return a(a), codegen


@intrinsic
def widen(typingctx, v, half):
    """VecD of the float32 lanes half * HALF ... (half * HALF + HALF - 1) of the Vec v; half a literal 0 or 1."""
    if not isinstance(half, types.IntegerLiteral) or half.literal_value not in (0, 1):
        raise numba.TypingError("simd.widen: half must be a literal 0 or 1")
    first = half.literal_value * HALF

    def codegen(context, builder, sig, args):
        mask = ir.Constant(ir.VectorType(_INT32, HALF), list(range(first, first + HALF)))
        return builder.fpext(builder.shuffle_vector(args[0], args[0], mask), vec_d.llvm)

    return vec_d(vec, half), codegen


@intrinsic
def narrow(typingctx, lo, hi):
    """Vec of two VecD halves (lanes 0 ... HALF - 1 from lo), each value rounded to float32."""

    def codegen(context, builder, sig, args):
        halves = [builder.fptrunc(arg, ir.VectorType(ir.FloatType(), HALF)) for arg in args]
        return builder.shuffle_vector(halves[0], halves[1], ir.Constant(_INTS, list(range(LANES))))

    return vec(vec_d, vec_d), codegen


@intrinsic
def vmin(typingctx, a, b):
    """Lane-wise minimum of two vectors of one type."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.minnum.{a.suffix}", a, args[0], args[1])

    return a(a, b), codegen


@intrinsic
def _times_pow2_neg(typingctx, p, m):
    """p 2^-m per lane, for integral float32 lanes m whose product stays a normal float32: the exponent bits
    of p less m (no multiplication)."""

    def codegen(context, builder, sig, args):
        shift = builder.shl(builder.fptosi(args[1], _INTS), ir.Constant(_INTS, [23] * LANES))
        return builder.bitcast(builder.sub(builder.bitcast(args[0], _INTS), shift), vec.llvm)

    return vec(vec, vec), codegen


@numba.njit(inline="always", fastmath=True)
def exp_neg(x):
    """Lane-wise exp(-x) for x >= 0 (a Vec): the operations of `regression.block._exp_neg`, bit for bit.
    Relative error < 5e-7 (float32 rounding; the polynomial's own is 9.2e-8); exp(-0) = 1; x beyond
    EXP_NEG_LIMIT gives exp(-EXP_NEG_LIMIT)."""
    xc = vmin(x, splat(np.float32(EXP_NEG_LIMIT)))
    m = floor(xc * np.float32(LOG2E) + np.float32(0.5))
    g = m * np.float32(LN2) - xc  # exp(-x) = 2^-m e^g, |g| <= ln2 / 2
    return _times_pow2_neg(exp_poly(g), m)


@numba.njit(inline="always")
def exp_poly(g):
    """e^g for |g| <= ln2 / 2 by `EXP_POLY` (Horner), for a float32 or a Vec g: the shared part of `exp_neg`
    and its scalar twin (inlined: the caller's fast-math flags, hence its fused multiply-adds)."""
    p = g * np.float32(EXP_POLY[5]) + np.float32(EXP_POLY[4])
    p = p * g + np.float32(EXP_POLY[3])
    p = p * g + np.float32(EXP_POLY[2])
    p = p * g + np.float32(EXP_POLY[1])
    return p * g + np.float32(EXP_POLY[0])


@intrinsic
def bits_to_float32(typingctx, bits):
    """Reinterpret int32 bits as a float32 (scalar numba code)."""

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@intrinsic
def float32_to_bits(typingctx, value):
    """Reinterpret a float32's bits as int32 (scalar numba code); inverse of `bits_to_float32`."""

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], _INT32)

    return types.int32(types.float32), codegen
