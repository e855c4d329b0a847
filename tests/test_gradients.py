"""Derivatives of ``solve`` (ilqg/implicit.py, docs/derivation.md §16) against central finite
differences of re-solves, and the optimal cost's gradient in x0 against the value function's 2 s_0.

The finite differences re-solve with tight tolerances and are Richardson-extrapolated over two
steps (the truncation error of a central difference is O(h^2); the re-solves are accurate to about
1e-9 relative, which bounds h from below). Every problem's arrays move at once along one random
direction (x0, targets, weights, limits, the noise scale sigma_u), so one pair of re-solves checks
the derivative in all of them.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr import Options, Problem, QuadraticCost, Status, solve
from delayed_ilqr.ilqg import implicit
from delayed_ilqr.models import arm2

from comparisons import WorstDifference, rel_err

worst = WorstDifference("derivative against finite differences of re-solves")
report_worst = worst.fixture()

TIGHT = Options(tol_grad=1e-13, tol_cost=1e-15, max_iterations=400)


def direction(problem: Problem, seed: int = 0) -> Problem:
    """A random tangent of the problem's leaves, relative to their size: symmetric for matrices
    (weights stay symmetric), zero for infinite limits."""
    rng = np.random.default_rng(seed)

    def one(leaf):
        leaf = np.asarray(leaf, float)
        r = rng.standard_normal(leaf.shape)
        if leaf.ndim == 2:
            return 0.5 * (r + r.T) * np.abs(leaf)
        return np.where(np.isfinite(leaf), r * (np.abs(leaf) + (0.1 if leaf.ndim == 1 else 0.0)), 0.0)

    return jax.tree_util.tree_map(one, problem)


def along(problem: Problem, tangent: Problem, t):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(jnp.isfinite(a), a + t * b, a), problem, tangent)


def outputs(sol):
    """The solution's differentiable outputs, by name."""
    out = dict(u=sol.u, x=sol.x, cost=sol.cost, expected_cost=sol.expected_cost, L=sol.policy.state_feedback,
               M=sol.policy.delay_feedback)
    if sol.policy.estimator is not None:            # with sensors, the filter's gains too
        out.update(Kd=sol.policy.estimator.delayed_gain, Kc=sol.policy.estimator.current_gain)
    return out


def richardson(f, h):
    """(4 D(h/2) - D(h)) / 3 of the central differences D of f (a dict of arrays) at 0."""
    def central(step):
        plus, minus = f(step), f(-step)
        return {k: (plus[k] - minus[k]) / (2 * step) for k in plus}
    coarse, fine = central(h), central(h / 2)
    return {k: (4 * fine[k] - coarse[k]) / 3 for k in fine}


def _derivatives(problem: Problem, tangent: Problem, u_init, options: Options, weights_seed=None):
    """One compiled function of t: (the solution's outputs at ``problem`` + t ``tangent``, their
    derivative along ``tangent`` in forward mode, the solution's status, and with ``weights_seed``
    random weights in [0.5, 1] for every output with the derivative of each output's weighted
    sum in reverse mode, stacked). One program serves the re-solves of the finite differences and
    both modes (jax.linearize, then the transpose of the same linear map, as jax.vjp does), so a
    problem compiles its differentiated solve once, not once per mode."""
    def at(t):
        sol = solve(along(problem, tangent, t), u_init, options)
        return outputs(sol), sol.status

    @jax.jit
    def run(t):
        values, forward_at, status = jax.linearize(at, t, has_aux=True)
        forward = forward_at(jnp.ones_like(t))
        if weights_seed is None:
            return values, forward, status, None, None
        rng = np.random.default_rng(weights_seed)           # the outputs' shapes are known when tracing
        weights = {k: rng.uniform(0.5, 1.0, np.shape(v)) for k, v in values.items()}
        # the cotangent of output k's weighted sum: its weights on k, zero on the others
        cotangents = {k: jnp.stack([weights[k] if i == j else jnp.zeros_like(weights[k]) for i in range(len(weights))])
                      for j, k in enumerate(weights)}
        backward = jax.vmap(lambda c: jax.linear_transpose(forward_at, t)(c)[0])(cotangents)
        return values, forward, status, weights, backward

    return run


def check_against_fd(name, problem, u_init, h, rtol, seed=0, reverse=True):
    """Forward mode (every output) along one random direction against Richardson-extrapolated
    finite differences and, with ``reverse``, reverse mode (random weighted sums of every output)
    against forward mode."""
    derivatives = _derivatives(problem, direction(problem, seed), u_init, TIGHT, seed + 1 if reverse else None)
    _, forward, status, weights, backward = derivatives(0.0)
    assert Status(int(status)).converged, status
    fd = richardson(lambda t: derivatives(t)[0], h)
    for key, value in fd.items():
        if value.size == 0 or not np.any(value):
            continue
        err = rel_err(forward[key], value)
        worst.record(err, f"{name} forward {key}")
        assert err < rtol, (name, key, err)
    if not reverse:
        return
    # reverse mode against forward mode: the transposed computation, checked to the Krylov solve's
    # accuracy (the finite differences above already tie forward mode to the re-solves)
    for key, got in zip(weights, np.asarray(backward)):
        products = np.asarray(weights[key]) * np.asarray(forward[key])
        if not np.any(products):
            continue
        err = abs(got - np.sum(products)) / np.sum(np.abs(products))
        worst.record(err, f"{name} reverse {key}")
        assert err < 1e-8, (name, key, err)


def _limited(free: Problem, fraction: float) -> Problem:
    """``free`` with symmetric limits at ``fraction`` of its optimum's largest commands."""
    top = fraction * np.max(np.abs(np.asarray(solve(free, None, TIGHT).u)), axis=0)
    return free.replace(u_min=-top, u_max=top)


def _held(problem: Problem) -> int:
    """How many commands the KKT conditions hold at a limit at ``problem``'s optimum."""
    return int(np.sum(implicit.fixed_commands(problem, solve(problem, None, TIGHT).u, TIGHT.limit_margin)[0]))


def test_arm_noisy_limited_delayed_matches_finite_differences():
    """The suite's check of the three full-size ones below, in one problem: the noisy arm at 50 ms
    with limits at 0.7 of its noise-aware optimum's largest commands (11 commands held). Forward
    mode against re-solves in every output (sigma_u and the limits among the leaves): the
    noise-aware fixed point, whose dF/du is not symmetric, with the held commands following the
    limit. Reverse mode against forward mode on the arm (most of this check's compilation) is in
    the full-size noisy check below; the suite holds it on the sensed point mass with additive noise
    (test_solve_with_sensors_matches_finite_differences)."""
    problem = _limited(arm2(delay=0.05, noise="benchmark"), 0.7)
    assert _held(problem) > 5
    check_against_fd("arm noisy limits 50 ms", problem, None, h=3e-4, rtol=1e-5, reverse=False)


# make bench (pytest -m full): the three cases one at a time; the suite keeps the combined one above
@pytest.mark.full
def test_arm_noisy_delayed_matches_finite_differences():
    """With noise: the derivative of the noise-aware fixed point, sigma_u among the leaves; dF/du is
    not symmetric, so reverse mode solves the transposed system (right-preconditioned)."""
    check_against_fd("arm noisy 50 ms", arm2(delay=0.05, noise="benchmark"), None, h=6e-4, rtol=1e-5)


@pytest.mark.full
def test_arm_limits_delayed_matches_finite_differences():
    """Commands at a limit follow the limit; the free ones solve (16.1) with those held. The
    limits are 0.7 of the unlimited optimum's largest commands, so that about 30 commands bind;
    h is small enough that no command crosses into or out of the active set."""
    problem = _limited(arm2(delay=0.05), 0.7)
    assert _held(problem) > 10
    check_against_fd("arm limits 50 ms", problem, None, h=3e-4, rtol=1e-5, reverse=False)


@pytest.mark.full
def test_arm_no_delay_noisy_limits_matches_finite_differences():
    """Delay 0 (the structured pass with no pending commands) with noise and limits at half the
    noise-aware optimum's largest commands: the held commands follow the limit, the free ones the
    noise-aware fixed point."""
    problem = _limited(arm2(delay=0.0, noise="benchmark"), 0.5)
    assert _held(problem) > 5
    check_against_fd("arm noisy limits 0 ms", problem, None, h=3e-4, rtol=1e-5, reverse=False)


def test_cost_gradient_in_x0_is_the_value_gradient(delay=0.05):
    """dJ*/dx0 = 2 s_0 (eq. 7's value function in the factor-2 convention): the envelope theorem,
    s_0 from the structured backward pass at the solution; reverse mode through the noise-free
    delayed solve against this independent value (measured 5.8e-9 at 50 ms, 2026-12-04)."""
    problem = arm2(delay=delay)

    def cost(dx0):
        sol = solve(along(problem, _only_x0(problem, dx0), 1.0), None, TIGHT)
        return sol.cost, (sol.x, sol.u)

    # the solution comes out of the same compiled program as the gradient (no second program)
    grad, (x, u) = jax.jit(jax.grad(cost, has_aux=True))(jnp.zeros(4))
    _, _, s, _ = implicit.value_at(problem, x, u, TIGHT.limit_margin)
    err = rel_err(grad, 2 * s[0])
    worst.record(err, f"dJ/dx0 = 2 s_0 at {delay} s")
    assert err < 1e-7, err


def _only_x0(problem, dx0):
    """A tangent that moves x0 by dx0 and nothing else."""
    zero = jax.tree_util.tree_map(jnp.zeros_like, problem)
    zero.x0 = dx0
    return zero


def test_unconverged_solve_gives_nan_derivatives():
    """A solve stopped by the iteration limit is not at a root of the optimality conditions: its
    derivatives are NaN, and its status says why."""
    problem = arm2(delay=0.05)
    opts = Options(max_iterations=2)

    def cost(dx0):
        sol = solve(along(problem, _only_x0(problem, dx0), 1.0), None, opts)
        return sol.cost, sol.status

    # the status comes out of the same compiled program as the derivative (no second program)
    (value, status), grad = jax.jit(jax.value_and_grad(cost, has_aux=True))(jnp.zeros(4))
    assert np.isfinite(value)
    assert np.all(np.isnan(grad))
    assert status == Status.MAX_ITERATIONS


def test_gradient_under_vmap():
    """vmap of a gradient over problems equals the gradients one at a time."""
    problem = arm2()
    targets = problem.cost.x_target + jnp.array([[0.0, 0.0, 0.0, 0.0], [0.05, -0.05, 0.0, 0.0]])

    def final_speed(target):
        cost = problem.cost._replace(x_target=target)
        sol = solve(along(problem.replace(cost=cost), _only_x0(problem, jnp.zeros(4)), 0.0), None, TIGHT)
        return jnp.sum(sol.x[-1, 2:] ** 2) + sol.cost

    batched = jax.jit(jax.vmap(jax.grad(final_speed)))(targets)
    one = jax.jit(jax.grad(final_speed))         # compiled once for both targets, not traced per call
    for target, row in zip(targets, batched):
        assert rel_err(row, one(target)) < 1e-9


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DampedMass:
    """A point mass with viscous damping b (a pytree leaf: differentiable) and delayed force."""

    b: float

    def __call__(self, x, u, ud):
        return jnp.array([x[1], ud[0] - self.b * x[1]])


def test_dynamics_parameter_of_a_pytree_dynamics():
    """The fields of a dynamics registered as a pytree are leaves of the Problem, differentiable."""
    cost = QuadraticCost(P=jnp.zeros((2, 2)), Q=1e-2 * jnp.eye(1), P_final=jnp.diag(jnp.array([10.0, 1.0])),
                         x_target=jnp.array([1.0, 0.0]))
    problem = Problem(DampedMass(0.5), x0=jnp.zeros(2), dt=0.05, horizon=30, delay_steps=3, cost=cost)
    assert any(leaf is problem.dynamics.b for leaf in jax.tree_util.tree_leaves(problem))

    def cost_at(b):
        return solve(Problem(DampedMass(b), x0=jnp.zeros(2), dt=0.05, horizon=30, delay_steps=3, cost=cost),
                     None, TIGHT)

    def f(b):
        sol = cost_at(b)
        return sol.expected_cost + jnp.sum(sol.u ** 2)

    grad = jax.jit(jax.grad(f))(0.5)             # compiled whole (outside a jit, each part compiles apart)
    fd = richardson(lambda t: {"f": f(0.5 + t)}, 1e-3)["f"]
    err = abs(grad - fd) / abs(fd)
    worst.record(err, "damped mass, d/db")
    assert err < 1e-6, err


@dataclasses.dataclass(frozen=True)
class _AdditiveForce:
    """Additive force noise on the point mass: the filter is the Kalman filter, no alternation."""

    def __call__(self, x, u, ud):
        return jnp.concatenate([jnp.zeros((2, 2), x.dtype), 0.5 * jnp.eye(2, dtype=x.dtype)])


@pytest.mark.parametrize("noise", ["additive", pytest.param("signal-dependent", marks=pytest.mark.full)])
def test_solve_with_sensors_matches_finite_differences(noise):
    """With delayed sensors (the point mass seen 1 step late) the solve is differentiable in both
    modes, the filter's gains included, in every array of the problem (the sensors' H and G too):
    before, reverse mode raised JAX's "Reverse-mode differentiation does not work for
    lax.while_loop" (Todorov's alternation). With signal-dependent noise the alternation runs, and
    its derivative is that of the alternations it ran."""
    from delayed_ilqr.models import point_mass
    problem = point_mass(delay=0.02, noise=True, sensory_delay=0.01)
    if noise == "additive":
        problem = problem.replace(noise=_AdditiveForce())
        check_against_fd(f"sensed point mass, {noise} noise", problem, None, h=1e-4, rtol=1e-5)
        return
    # the alternation keeps or rejects each redesign by comparing exact costs, so its result is only
    # piecewise smooth in the problem (finite differences across those choices differ by 1.6e-4):
    # reverse mode is checked against forward mode, the derivative of the same computation
    _, forward, _, weights, backward = _derivatives(problem, direction(problem), None, Options(), 1)(0.0)
    forward = np.array([np.sum(np.asarray(weights[k]) * np.asarray(forward[k])) for k in weights])
    assert np.all(np.isfinite(forward)) and np.any(forward != 0)
    assert rel_err(backward, forward) < 1e-8, (backward, forward)


def test_grad_over_a_framed_problem_equals_the_unframed_one():
    """``jax.grad`` over a whole framed problem (its delay a leaf): before, JAX refused the integer
    delay ("grad requires real- or complex-valued inputs"); now the gradient in every array equals
    the unframed problem's, and the delay's own entry is zero (a whole number of steps)."""
    from delayed_ilqr.models import point_mass
    problem = point_mass(delay=0.02, noise=True)
    gradient = jax.jit(jax.grad(lambda p: solve(p, None, TIGHT).expected_cost))
    framed = gradient(problem.replace(delay_frame=4))
    plain = gradient(problem)
    for got, want in zip(jax.tree_util.tree_leaves((framed.x0, framed.cost)),
                         jax.tree_util.tree_leaves((plain.x0, plain.cost))):
        assert rel_err(got, want) < 1e-8
    assert int(framed.delay_steps) == 0
