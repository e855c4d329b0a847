"""delayed-ilqr: iterative LQG for nonlinear stochastic systems with control (input) delay.

Implements Ju, Qin & Fu, "Extending iLQR method with control delay" (Theorem 1, with the
corrections listed in ``docs/derivation.md``) and builds a full solver around it.

Notation (used in names throughout the library; arrays are time-major):

| symbol | meaning |
|---|---|
| n, d, p | number of states, controls, noise columns |
| l | ``delay_steps``: the command u_k acts on the plant from step k + l (tau = l dt) |
| L | ``delay_frame``: with it, the pending commands live in L >= l slots and l is data, so problems of different delays share one compiled solver (docs/derivation.md §17) |
| K | ``horizon``: controls u_0..u_{K-1}, states x_0..x_K |
| x, u, ud | state, command sent now, command acting now (ud = u_{k-l}; u_k = 0 for k < 0) |
| xs, us | trajectories [K+1, n], [K, d] |
| A, B0, B1 | eq. (3): dx_{k+1} = A dx_k + B0 du_k + B1 du_{k-l} + noise |
| c, C0, C1 | eq. (3): noise column j = c_j + C0_j du_k + C1_j du_{k-l}, times xi_j ~ N(0, 1) |
| d_tilde, d, D, e, E | eq. (4): cost_k = d_tilde + 2 dx'd + dx'D dx + 2 du'e + du'E du |
| I, L, M | eq. (6): du_k = I_k + L_k dx_k + sum_i M_k^i du_{k+i-l} |
| S, s, s_tilde, R, Rt, r | eq. (7): coefficients of the cost-to-go J(k) |
| H | Hessian of J(k-1) in du_{k-1} (the quantity that must be positive definite) |
| l_s, y | sensory delay in steps; y_k = h(x_{k-l_s}) + G v_k, the measurement that arrives at k |
| x_hat | E[dx_k &#124; I_k], the delayed filter's estimate; Kd, Kc its gains (``lqg.estimator``) |

Importing the package changes nothing in the process: no environment variable, no JAX setting.
Two lines that a program using it runs first, before any JAX computation:

    jax.config.update("jax_enable_x64", True)   # required: the solver refuses float32
    delayed_ilqr.configure_cpu()                 # optional: XLA flags that halve small solves

The library needs float64 and says so with a ``ValueError`` that names the first line, rather
than switching precision for its own computations (see ``_precision``). [`configure_cpu`][delayed_ilqr.configure_cpu]
adds two of XLA's CPU flags to ``XLA_FLAGS`` so that XLA compiles the solver's small loops as
single functions (see ``_cpu``); it warns when it comes too late to take effect.
[`enable_compilation_cache`][delayed_ilqr.enable_compilation_cache] (opt-in; the command line turns it on) keeps compiled solvers on
disk, so that the next process reads them instead of compiling again (see ``_cache``).
"""
from . import lqg, models, mpc
from ._cache import default_cache_dir, enable_compilation_cache
from ._cpu import configure_cpu
from .problem import GeneralCost, Problem, QuadraticCost
from .delay_jitter import DelayJitter
from .observation import Observation
from .solution import Estimator, Policy, Solution, Status, Trace
from .fused_estimator import FusedEstimator
from .ilqg.solver import solve
from .ilqg.continuation import Continuation, Starts, augmented_lagrangian_start, solve_from_starts
from .options import Options
from .simulate import Runs, simulate
from .saving import load, load_metadata

__all__ = ["lqg", "models", "mpc", "configure_cpu", "enable_compilation_cache", "default_cache_dir", "sweep", "open_sweep",
           "Problem", "DelayJitter", "QuadraticCost", "GeneralCost", "Observation", "Options", "solve",
           "solve_from_starts", "augmented_lagrangian_start", "Starts", "Continuation", "Solution", "Policy",
           "Estimator", "FusedEstimator", "Status", "Trace", "simulate", "Runs", "load", "load_metadata"]
__version__ = "0.1.0"


def __getattr__(name):
    # sweep and open_sweep need the ``sweep`` extra (xarray, zarr, dask): imported on first use
    if name in ("sweep", "open_sweep"):
        from . import sweeps
        return getattr(sweeps, name)
    raise AttributeError(f"module 'delayed_ilqr' has no attribute {name!r}")
