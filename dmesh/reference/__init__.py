"""Naive NumPy/SciPy references for the native kernels, for tests, benchmarks and users.

They are slow and simple on purpose: each is an independent way to compute what a native kernel computes.
"""
