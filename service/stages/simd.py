"""Explicit float32 SIMD vectors for numba kernels: `Vec`, LANES lanes held in one LLVM vector value.

numba's auto-vectoriser only vectorises innermost loops, so a kernel whose accumulators must stay in
registers across an inner loop (the window offsets of a regression) is left scalar or spills every
accumulator to memory on every step. With `Vec` a kernel writes the vector code itself: a Vec local
variable is an LLVM `<LANES x float>` value, which the register allocator keeps in a SIMD register.
LANES = 16 is one AVX-512 register; on narrower hardware LLVM splits each operation (two AVX2 ops,
four NEON ops), so the same kernel is correct everywhere.

In numba code (all arithmetic in float32, fast-math: fused multiply-adds and reassociation allowed):
    v = load(array, (i, j, k))    # LANES consecutive float32 along the last axis, from array[i, j, k]
    store(array, (i, j, k), v)    # the reverse; C-contiguous arrays, indices unchecked
    v = splat(x)                  # every lane = float32 x
    v + w, v - w, v * w, v / w    # lane-wise; either side may be a Python/numpy float
    vmax(v, w), floor(v), exp_neg(v)
`exp_neg` is the vector twin of `local_regression._exp_neg` (the same polynomial, the same values).
"""

from __future__ import annotations

import operator

import llvmlite.ir as ir
import numba
import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model

LANES = 16  # float32 lanes of one Vec: one AVX-512 register

_FLOAT = ir.FloatType()
_VECTOR = ir.VectorType(_FLOAT, LANES)
_INTS = ir.VectorType(ir.IntType(32), LANES)
_FAST = ("fast",)


class VecType(types.Type):
    """numba type of a Vec: LANES float32 values in one LLVM vector."""

    def __init__(self) -> None:
        super().__init__(name=f"Vec{LANES}xf32")


vec = VecType()


@register_model(VecType)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _VECTOR)


def _pointer(context, builder, aryty, ary, index, indices):
    """LLVM pointer to array[indices], as a pointer to a whole Vec."""
    array = context.make_array(aryty)(context, builder, ary)
    items = cgutils.unpack_tuple(builder, index, len(indices))
    items = [context.cast(builder, item, ty, types.intp) for item, ty in zip(items, indices, strict=True)]
    ptr = cgutils.get_item_pointer(context, builder, aryty, array, items)
    return builder.bitcast(ptr, _VECTOR.as_pointer())


def _check_access(array, index) -> None:
    if not (isinstance(array, types.Array) and array.dtype == types.float32 and array.layout == "C"):
        raise numba.TypingError(f"simd: needs a C-contiguous float32 array, got {array}")
    if not (isinstance(index, types.BaseTuple) and len(index) == array.ndim):
        raise numba.TypingError(f"simd: needs a tuple of {array.ndim} indices, got {index}")


@intrinsic
def load(typingctx, array, index):
    """Vec of array[index] and the LANES - 1 values after it along the last axis (unaligned load)."""
    _check_access(array, index)

    def codegen(context, builder, sig, args):
        return builder.load(_pointer(context, builder, array, args[0], args[1], index.types), align=4)

    return vec(array, index), codegen


@intrinsic
def store(typingctx, array, index, value):
    """Write a Vec to array[index] and the LANES - 1 places after it along the last axis."""
    _check_access(array, index)

    def codegen(context, builder, sig, args):
        builder.store(args[2], _pointer(context, builder, array, args[0], args[1], index.types), align=4)
        return context.get_dummy_value()

    return types.void(array, index, vec), codegen


@intrinsic
def splat(typingctx, x):
    """Vec with every lane = float32(x)."""

    def codegen(context, builder, sig, args):
        value = context.cast(builder, args[0], sig.args[0], types.float32)
        one = builder.insert_element(ir.Constant(_VECTOR, ir.Undefined), value, ir.Constant(ir.IntType(32), 0))
        return builder.shuffle_vector(one, one, ir.Constant(_INTS, [0] * LANES))

    return vec(x), codegen


def _binary(name: str):
    @intrinsic
    def op(typingctx, a, b):
        def codegen(context, builder, sig, args):
            return getattr(builder, name)(args[0], args[1], flags=_FAST)

        return vec(vec, vec), codegen

    return op


_add, _sub, _mul, _div = (_binary(name) for name in ("fadd", "fsub", "fmul", "fdiv"))


def _overload_operator(operation, op) -> None:
    @overload(operation)
    def impl(a, b):
        if isinstance(a, VecType) and isinstance(b, VecType):
            return lambda a, b: op(a, b)
        if isinstance(a, VecType) and isinstance(b, (types.Float, types.Integer)):
            return lambda a, b: op(a, splat(b))
        if isinstance(a, (types.Float, types.Integer)) and isinstance(b, VecType):
            return lambda a, b: op(splat(a), b)
        return None


for _operation, _op in ((operator.add, _add), (operator.sub, _sub), (operator.mul, _mul), (operator.truediv, _div)):
    _overload_operator(_operation, _op)
    _overload_operator({operator.add: operator.iadd, operator.sub: operator.isub, operator.mul: operator.imul,
                        operator.truediv: operator.itruediv}[_operation], _op)  # fmt: skip


def _call_llvm(builder, name: str, *args):
    module = builder.module
    fn = cgutils.get_or_insert_function(module, ir.FunctionType(_VECTOR, [_VECTOR] * len(args)), name)
    return builder.call(fn, args)


@intrinsic
def vmax(typingctx, a, b):
    """Lane-wise maximum of two Vecs."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.maxnum.v{LANES}f32", args[0], args[1])

    return vec(vec, vec), codegen


@intrinsic
def floor(typingctx, a):
    """Lane-wise floor of a Vec."""

    def codegen(context, builder, sig, args):
        return _call_llvm(builder, f"llvm.floor.v{LANES}f32", args[0])

    return vec(vec), codegen


@intrinsic
def _pow2(typingctx, n):
    """2^n per lane for integral float lanes n in [-126, 127]: the exponent bits of a float32."""

    def codegen(context, builder, sig, args):
        bits = builder.add(builder.fptosi(args[0], _INTS), ir.Constant(_INTS, [127] * LANES))
        return builder.bitcast(builder.shl(bits, ir.Constant(_INTS, [23] * LANES)), _VECTOR)

    return vec(vec), codegen


@numba.njit(inline="always", fastmath=True)
def exp_neg(x):
    """Lane-wise exp(-x) for x >= 0 (a Vec): the polynomial of `local_regression._exp_neg`, bit for bit.
    Relative error 3e-7 near 0, growing with x to ~6e-6 at 80 (float32 rounding of x log2 e); x beyond 87
    gives exp(-87)."""
    t = vmax(np.float32(0.0) - x, splat(np.float32(-87.0))) * np.float32(1.4426950408889634)  # log2(e)
    n = floor(t + np.float32(0.5))
    f = (t - n) * np.float32(0.6931471805599453)  # |f| <= ln2 / 2
    p = f * np.float32(1.0 / 720.0) + np.float32(1.0 / 120.0)
    p = p * f + np.float32(1.0 / 24.0)
    p = p * f + np.float32(1.0 / 6.0)
    p = p * f + np.float32(0.5)
    p = p * f + np.float32(1.0)
    p = p * f + np.float32(1.0)
    return p * _pow2(n)
