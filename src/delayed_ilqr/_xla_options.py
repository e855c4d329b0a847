"""XLA's CPU backend, configured for loops of many small operations.

XLA on CPU runs each operation of a loop body as a separate thunk, at about 0.1 to 0.2 us each,
and the time steps of motor-control problems are small: P1's backward step is 29 such operations
on [4, 20] matrices. XLA compiles a ``while`` loop whose body reads and writes less than
``xla_cpu_small_while_loop_byte_threshold`` bytes per iteration (1024 by default) into one
function instead, with no thunk per operation, unless the loop holds a library call. Two settings
make that cover the scans of the solver:

* the threshold, raised to 1 MB (:func:`configure`, at import): per-step work that small is
  dominated by the per-operation cost, and larger loops keep the thunk runtime, which runs large
  products on both cores;
* ``solve``'s compilation without YNNPACK fusions (:data:`SOLVER_COMPILER_OPTIONS`): XLA turns some
  fused products into them (library calls), and P3's backward pass, with one such product a
  step, stayed a loop of thunks. From l d = 300 on the solver keeps them (``solver.compiled_solver``).

Whole solves, compiled, in separate processes alternately on the 2-core machine (medians, ms,
before / after): P1 0.82-0.84 / 0.33-0.42, P2 2.2-2.4 / 1.1-1.3, P3 22.5-23.1 / 17.5-19.2,
P4 at l = 1 2.9-3.5 / 0.87-0.98, at l = 10 4.4-6.5 / 1.9-2.0, at l = 100 27-29 / 20-21; the
augmented reference: P2 5.2-5.5 / 3.0-3.5, P4 at l = 10 15-19 / 6.7-9.7, P3 and P4 at l = 100
equal or faster.

The threshold is one of XLA's backend options, which only the ``XLA_FLAGS`` environment variable
sets (``jax.jit``'s ``compiler_options`` take no map-valued options), and XLA reads it when JAX
starts its backend: importing ``delayed_ilqr`` before the first JAX computation applies it. A value
the user set is kept (``1024`` restores XLA's default).
"""
from __future__ import annotations

import os

_OPTION = "xla_cpu_small_while_loop_byte_threshold"
SMALL_LOOP_BYTES = 1_000_000
SOLVER_COMPILER_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


def configure(environ=os.environ) -> None:
    """Adds the small-loop threshold to ``XLA_FLAGS`` unless it is already there."""
    flags = environ.get("XLA_FLAGS", "")
    if _OPTION not in flags:
        environ["XLA_FLAGS"] = f"{flags} --xla_backend_extra_options={_OPTION}={SMALL_LOOP_BYTES}".strip()
