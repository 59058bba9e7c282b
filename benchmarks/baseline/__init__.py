"""Frozen copies of the numba kernels as they were before issue 12 (commit aaa57ff), kept only
so the speed benchmarks can measure today's kernels against them in the same run. Not part of
the package; never imported by it."""
