"""A cache prefetch hint for Numba kernels (private): ``prefetch(arr, i)``.

Event kernels touch per-pixel state in the order events arrive, which for a large sensor is a
stream of cache misses (1280x720: 56 MB of AKF state, beyond any cache). Telling the CPU a few
events ahead which lines the kernel will need lets the misses overlap instead of stalling one
after another. A hint only: no fault, no effect on results, and ignored by CPUs without it.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["prefetch"]


def _intrinsic_name() -> str:
    """The overloaded intrinsic's name: opaque pointers (LLVM >= 16 here) mangle as ``p0``."""
    try:
        from llvmlite.binding import llvm_version_info
        major = llvm_version_info[0]
    except Exception:  # noqa: BLE001
        major = 16
    return "llvm.prefetch.p0" if major >= 16 else "llvm.prefetch.p0i8"


_NAME = _intrinsic_name()


@intrinsic
def prefetch(typingctx, arr, idx):
    """Prefetch the cache line holding element ``idx`` of the C-contiguous array ``arr``,
    counted over its flat storage (``pix * fields`` for a (pixels, fields) record array), for
    writing, kept in all cache levels. ``idx`` is not bounds-checked: a prefetch never faults."""
    if not isinstance(arr, types.Array) or not isinstance(idx, types.Integer):
        return None
    sig = types.void(arr, idx)

    def codegen(context, builder, signature, args):
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        i = context.cast(builder, args[1], idxty, types.intp)
        ptr = builder.gep(ary.data, [i])
        i8p = builder.bitcast(ptr, ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, _NAME)
        # rw = 1 (the kernels write what they read), locality = 3 (keep), cache type = 1 (data)
        builder.call(fn, [i8p, ir.Constant(i32, 1), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen
