"""Numerical kernels: how the mathematics is made fast on XLA's CPU backend, kept apart from it.

* `dense`: fused small products (``matmul``, ``matmul_t``, ``add_symmetric_product``), the
  unrolled Cholesky solve, and the CPU batching rule that turns a batch of fused products back
  into one library call.
* `scan`: ``packed_scan``, ``lax.scan`` with its per-step inputs and outputs packed into one
  array per dtype, run in blocks with a flush of deferred work.

The recursion and the models call these; they do not contain the tricks. Every kernel computes the
plain product, solve or scan it replaces (tests/test_dense.py, tests/test_scan.py), and the
measurements that justify each threshold are in docs/performance.md.
"""
