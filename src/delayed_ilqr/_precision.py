"""The library computes in float64 and refuses to run without it: `require_x64`.

Why refuse rather than switch precision for the library's own computations: in float32 the
solver still runs but wanders (P2 took 38 iterations instead of 9 and stopped at a cost 1e-6
off, with no error), and JAX's scoped switch (``with jax.enable_x64(True)``, jax 0.10) does not
make a library float64 on its own. Arrays built outside the scope are float32 (a ``Problem``
made there fails inside with a scan carry of mixed dtypes); inside a user's ``jax.jit`` traced
in float32 the solve fails on mixed int32 / int64 indices; and the float64 arrays it returns are
silently cast back to float32 by the next operation outside. Making it work would mean casting
every input and output at every entry point and still failing under the user's transformations.
JAX's float64 is one global line, which the error names.
"""
from __future__ import annotations

import jax

ENABLE_X64 = 'jax.config.update("jax_enable_x64", True)'


def require_x64(what: str) -> None:
    """Raises unless JAX computes in float64 here (globally, or in the enclosing trace).

    Args:
        what: the entry point, for the message (e.g. ``"solve"``).

    Raises:
        ValueError: when float64 is off; the message names the one line that turns it on.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(f"delayed_ilqr.{what} needs float64, which JAX has off by default: add "
                         f"`{ENABLE_X64}` at the top of the program, before creating any JAX array")
