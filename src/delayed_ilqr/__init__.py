"""delayed-ilqr: iterative LQG for nonlinear stochastic systems with control (input) delay.

Implements Ju, Qin & Fu, "Extending iLQR method with control delay" (Theorem 1, with the
corrections listed in ``docs/derivation.md``) and builds a full solver around it.

Notation (used in names throughout the library; arrays are time-major):

=========  =====================================================================================
n, d, p    number of states, controls, noise columns
l          ``delay_steps``: the command u_k acts on the plant from step k + l (tau = l dt)
K          ``horizon``: controls u_0..u_{K-1}, states x_0..x_K
x, u, ud   state, command sent now, command acting now (ud = u_{k-l}; u_k = 0 for k < 0)
xs, us     trajectories [K+1, n], [K, d]
A, B0, B1  eq. (3): dx_{k+1} = A dx_k + B0 du_k + B1 du_{k-l} + noise
c, C0, C1  eq. (3): noise column j = c_j + C0_j du_k + C1_j du_{k-l}, times xi_j ~ N(0, 1)
d_tilde, d, D, e, E   eq. (4): cost_k = d_tilde + 2 dx'd + dx'D dx + 2 du'e + du'E du
I, L, M    eq. (6): du_k = I_k + L_k dx_k + sum_i M_k^i du_{k+i-l}
S, s, s_tilde, R, Rt, r   eq. (7): coefficients of the cost-to-go J(k)
H          Hessian of J(k-1) in du_{k-1} (the quantity that must be positive definite)
=========  =====================================================================================

Importing the package enables float64 in JAX: a user who does nothing gets double precision. It
also sets two of XLA's CPU flags for the process, so that XLA compiles the solver's small loops as
single functions (see ``_xla_options``); they take effect when the package is imported before
JAX's first computation, and a flag the user set in ``XLA_FLAGS`` is kept.
"""
from . import _xla_options

_xla_options.configure()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from . import lqg  # noqa: E402
from .problem import GeneralCost, Problem, QuadraticCost  # noqa: E402
from .solution import Policy, Solution, Status, Trace  # noqa: E402
from .options import Options  # noqa: E402
from .ilqg.solver import solve  # noqa: E402
from .simulate import Runs, simulate  # noqa: E402

__all__ = ["lqg", "Problem", "QuadraticCost", "GeneralCost", "Options", "solve", "Solution", "Policy",
           "Status", "Trace", "simulate", "Runs"]
__version__ = "0.1.0"
