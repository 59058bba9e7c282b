"""Frozen copies of the numba kernels as they were before issue 12 (commit aaa57ff), and of
scoring's torch SSIM and zipfile reads (``scoring.py``), kept only so the speed benchmarks can
measure today's code against them in the same run. Not part of
the package; never imported by it."""
