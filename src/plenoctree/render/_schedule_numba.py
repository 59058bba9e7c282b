"""Dynamic scheduling of a numba ``prange`` loop: a shared counter hands out work items.

numba's ``prange`` gives each thread one contiguous run of the iteration space under the omp and
workqueue threading layers, also with ``numba.set_parallel_chunksize`` (numba's docs: only the
tbb layer schedules chunks dynamically); an image's cost sits where the object is, so at 16
threads the busiest thread had over twice the mean work on lego. The render kernel instead runs
one ``prange`` iteration per thread, each taking the next item from a counter until none is
left::

    counter = np.zeros(1, np.int64)
    for _ in prange(max(1, min(threads, n_items))):     # threads: numba.get_num_threads()
        while True:
            item = next_item(counter)
            if item >= n_items:
                break
            ...

Which thread runs an item changes from run to run, what an item computes does not: a kernel
whose items write disjoint outputs gives the same bits with any schedule. (``threads`` is an
argument of the kernel: ``numba.get_num_threads()`` called inside a kernel keeps numba from
caching it on disk.) ``benchmarks/_balance.py`` counts the per-thread work of both schedules on
real images.
"""

from __future__ import annotations

from llvmlite import ir as _ir
from numba import njit
from numba.core import cgutils as _cgutils
from numba.core import types as _types
from numba.extending import intrinsic

__all__ = ["next_item"]


@intrinsic
def _fetch_add_one(typingctx, arr):
    """Atomically ``old = arr[0]; arr[0] += 1``; returns ``old`` (``arr``: int64 1-D)."""
    sig = _types.int64(arr)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        zero = context.get_constant(_types.intp, 0)
        ptr = _cgutils.get_item_pointer(context, builder, aryty, ary, [zero], wraparound=False)
        return builder.atomic_rmw("add", ptr, _ir.Constant(_ir.IntType(64), 1), "monotonic")

    return sig, codegen


@njit(cache=True, inline="always")
def next_item(counter):
    """The next unclaimed work item (0, 1, 2, ... across all threads; each returned once):
    an atomic increment of ``counter[0]`` (int64 ``[1]``, zero before the loop)."""
    return _fetch_add_one(counter)
