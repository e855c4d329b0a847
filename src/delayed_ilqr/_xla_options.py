"""XLA's CPU backend, configured for loops of many small operations (``XLA_FLAGS``, at import).

XLA on CPU runs each operation of a loop body as a separate thunk, at about 0.1 to 0.2 us each,
and the time steps of motor-control problems are small: P1's backward step is 29 such operations
on [4, 20] matrices. XLA compiles a ``while`` loop whose body reads and writes less than
``xla_cpu_small_while_loop_byte_threshold`` bytes per iteration (1024 by default) into one
function instead, with no thunk per operation, unless the loop holds a library call. Two flags
make that cover the solver's scans:

* the threshold, raised to 1 MB: per-step work that small is dominated by the per-operation
  cost; larger loops keep the thunk runtime, whose large products use both cores and the
  library's kernels (at 100 MB the augmented P3 took 3.5 s instead of 0.6 s);
* no YNNPACK single dots (``--xla_cpu_experimental_ynn_fusion_type=-individual_dot``; XLA's
  default hands single dots, some of which it makes from fused products, to that library): a loop
  that holds one is never compiled as one function, and P3's backward pass, with one a step,
  stayed a loop of thunks. Its other fusions stay: without them too (``=``, nothing) the loops
  are the same, but P4's solver at l = 1 held 1.26 MB instead of 1.04.
  ``solver.compiled_solver`` turns them back on from l d = 300 (:data:`LIBRARY_DOTS`), where the
  deferred R update's large products run faster through them.

Whole solves, compiled, in separate processes alternately on the 2-core machine (medians, ms,
before / after): P1 0.82-0.84 / 0.33-0.42, P2 2.2-2.4 / 1.1-1.3, P3 22.5-23.1 / 14.8-19.2,
P4 at l = 1 2.9-3.5 / 0.87-0.98, at l = 10 4.4-6.5 / 1.9-2.0, at l = 100 27-29 / 20-21; the
augmented reference: P2 5.2-5.5 / 3.0-3.5, P4 at l = 10 15-19 / 6.7-9.7, P3 and P4 at l = 100
equal or faster.

Both are process-wide, and only ``XLA_FLAGS`` sets the threshold (``jax.jit``'s
``compiler_options`` take no map-valued options); XLA reads it when JAX starts its backend, so
importing ``delayed_ilqr`` before the first JAX computation applies them. A flag the user set
is kept: ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024`` and
``--xla_cpu_experimental_ynn_fusion_type=+individual_dot`` restore XLA's defaults.
"""
from __future__ import annotations

import os

SMALL_LOOP_BYTES = 1_000_000
# (name in XLA_FLAGS, flag): each is added unless XLA_FLAGS already names it
_FLAGS = (("xla_cpu_small_while_loop_byte_threshold",
           f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"),
          ("xla_cpu_experimental_ynn_fusion_type", "--xla_cpu_experimental_ynn_fusion_type=-individual_dot"))
# YNNPACK's single dots back, for one compilation (``jax.jit``'s compiler_options name the whole list)
LIBRARY_DOTS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}


def configure(environ=os.environ) -> None:
    """Adds the small-loop threshold and YNNPACK's setting to ``XLA_FLAGS``, each unless the user
    set it there."""
    flags = environ.get("XLA_FLAGS", "")
    for name, flag in _FLAGS:
        if name not in flags:
            flags = f"{flags} {flag}".strip()
    environ["XLA_FLAGS"] = flags
