"""Time in the task: a via-point reach with a time-varying force field, against references that
compute the time themselves.

The plant is a point mass (position, velocity in 2-D) with nonlinear drag, pushed by a force field
that switches direction over time; the cost pulls the mass through a via-point at t_via and to a
target at rest at the end. The reference rollout and cost below are written here, step by step
with t_k = k dt from the loop index, independent of the library's time plumbing
(``Problem.step_times``); L-BFGS-B over all commands on them is the independent optimum.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import linearize

DT, K = 0.01, 50
T_VIA, VIA, TARGET = 0.25, jnp.array([0.05, 0.04]), jnp.array([0.1, 0.0])


def field(t):
    """A force field [N/kg] that turns over the movement: time-varying, not state-dependent."""
    return jnp.array([0.5 * jnp.cos(2 * jnp.pi * t / 0.5), 1.5 * jnp.sin(2 * jnp.pi * t / 0.5)])


def dynamics(x, u, ud, t):
    v = x[2:]
    drag = 0.5 * v + 2.0 * v * jnp.sqrt(v @ v + 1e-4)           # smooth nonlinear drag
    return jnp.concatenate([v, ud - drag + field(t)])


def running(x, u, params, t):
    bump = jnp.exp(-0.5 * ((t - params["t_via"]) / 0.02) ** 2)      # the via-point acts around t_via
    err = x[:2] - params["via"]
    return params["w_via"] * bump * (err @ err) + 1e-4 * (u @ u)


def final(x, params, t):
    err = jnp.concatenate([x[:2] - params["target"], 0.2 * x[2:]])
    return (1.0 + 0.0 * t) * (err @ err)


PARAMS = dict(via=VIA, target=TARGET, t_via=T_VIA, w_via=50.0)


def via_problem(delay_steps):
    return di.Problem(dynamics, jnp.zeros(4), DT, K, delay_steps,
                      di.GeneralCost(running, final, PARAMS, time_dependent=True), n_controls=2,
                      time_dependent=True, name="via-point")


def reference_rollout(us, delay_steps, f=dynamics):
    """x_{k+1} = x_k + dt f(x_k, u_k, u_{k-l}, k dt), looping over the index k."""
    padded = jnp.concatenate([jnp.zeros((delay_steps, 2)), us])           # padded[k] = u_{k-l}

    def step(x, k):
        x_new = x + DT * f(x, us[k], padded[k], k * DT)
        return x_new, x_new

    return jnp.concatenate([jnp.zeros((1, 4)), jax.lax.scan(step, jnp.zeros(4), jnp.arange(K))[1]])


def reference_cost(us, delay_steps):
    xs = reference_rollout(us, delay_steps)
    ks = jnp.arange(K)
    return DT * jnp.sum(jax.vmap(lambda k: running(xs[k], us[k], PARAMS, k * DT))(ks)) + final(xs[K], PARAMS, K * DT)


def reference_optimum(delay_steps, u0):
    fun = jax.jit(lambda v: reference_cost(v.reshape(K, 2), delay_steps))
    grad = jax.jit(jax.grad(lambda v: reference_cost(v.reshape(K, 2), delay_steps)))
    u, best = np.asarray(u0, float).ravel(), float(fun(jnp.asarray(u0).ravel()))
    for _ in range(20):                      # rescaled restarts, as tests/direct.py
        scale = 1.0 / best
        u = scipy.optimize.minimize(lambda v: scale * float(fun(v)), u, jac=lambda v: scale * np.asarray(grad(v)),
                                    method="L-BFGS-B", options=dict(maxiter=20000, ftol=1e-16, gtol=1e-14,
                                                                      maxcor=50)).x
        cost = float(fun(jnp.asarray(u)))
        if best - cost <= 1e-11 * abs(cost):
            return min(cost, best)
        best = cost
    return best


@pytest.mark.parametrize("delay_steps", [0, 4])
def test_via_point_reach_matches_direct_reference(delay_steps):
    problem = via_problem(delay_steps)
    sol = di.solve(problem)
    assert sol.converged, sol.message
    # the library's rollout and cost of the solution are the reference's (time passed as k dt)
    np.testing.assert_allclose(sol.x, reference_rollout(sol.u, delay_steps), rtol=0, atol=1e-14)
    assert float(sol.cost) == pytest.approx(float(reference_cost(sol.u, delay_steps)), rel=1e-13)
    # and it is the optimum that L-BFGS-B finds on the reference (started from the solution, so
    # that both find the same local minimum; a lower reference cost would fail the test)
    assert float(sol.cost) <= reference_optimum(delay_steps, sol.u) * (1 + 1e-9)
    # the reach passes the via-point at t_via (within 5 mm) and ends at the target
    assert float(jnp.linalg.norm(sol.x[round(T_VIA / DT), :2] - VIA)) < 5e-3
    assert float(jnp.linalg.norm(sol.x[-1, :2] - TARGET)) < 5e-3


def test_linearization_sees_step_time():
    """A, B1 and c of step k are the derivatives at t_k = k dt (field and noise switched on at 0.2 s)."""
    def switched(x, u, ud, t):
        return dynamics(x, u, ud, t) * jnp.where(t >= 0.2, 2.0, 1.0)

    def noise(x, u, ud, t):
        return jnp.where(t >= 0.2, 0.1, 0.0) * jnp.eye(4)[:, :2]

    problem = di.Problem(switched, jnp.zeros(4), DT, K, 2, di.GeneralCost(running, final, PARAMS, time_dependent=True),
                         noise=noise, n_controls=2, time_dependent=True)
    us = 0.3 * jnp.ones((K, 2))
    xs = reference_rollout(us, 2, switched)
    lqg = jax.jit(linearize)(problem, xs, us)
    for k in (0, 19, 20, 35):
        t = k * DT
        ud = us[k - 2] if k >= 2 else jnp.zeros(2)
        np.testing.assert_allclose(lqg.B1[k], DT * jax.jacfwd(switched, argnums=2)(xs[k], us[k], ud, t), atol=1e-14)
        np.testing.assert_allclose(lqg.c[k], jnp.sqrt(DT) * noise(xs[k], us[k], ud, t).T, atol=0)
        np.testing.assert_allclose(lqg.d_tilde[k], DT * running(xs[k], us[k], PARAMS, t), rtol=1e-14)
    assert float(lqg.d_tilde[K]) == pytest.approx(float(final(xs[K], PARAMS, K * DT)), rel=1e-14)


@pytest.mark.parametrize("substeps", [1, 3])
def test_simulate_uses_step_and_substep_time(substeps):
    """Noise that starts at t = 0.2 s: every trial equals the nominal before it and spreads after;
    without noise the closed loop reproduces the reference integration with the sub-steps' times."""
    def noise(x, u, ud, t):
        return jnp.where(t >= 0.2, 0.05, 0.0) * jnp.eye(4)[:, 2:]

    problem = via_problem(3)
    sol = di.solve(problem)
    det = di.simulate(problem, sol.policy, 1, seed=0, substeps=substeps)
    runs = di.simulate(problem.replace(noise=noise), sol.policy, 8, seed=1, substeps=substeps)
    k_on = round(0.2 / DT)
    np.testing.assert_allclose(runs.x[:, :k_on + 1], np.broadcast_to(det.x[0, :k_on + 1], (8, k_on + 1, 4)), atol=1e-12)
    assert float(np.min(np.std(np.asarray(runs.x[:, k_on + 2:, 2]), axis=0))) > 0
    # deterministic: the policy applied to the plant integrated with sub-steps at k dt + j h
    h, x = DT / substeps, jnp.zeros(4)
    for k in range(K):
        ud = det.u[0, k - 3] if k >= 3 else jnp.zeros(2)
        for j in range(substeps):
            x = x + h * dynamics(x, det.u[0, k], ud, k * DT + j * h)
        np.testing.assert_allclose(det.x[0, k + 1], x, atol=1e-13)


def test_time_flags_are_checked():
    with pytest.raises(ValueError, match=r"dynamics\(x, u, ud, t\) failed"):
        di.Problem(lambda x, u, ud: x, jnp.zeros(4), DT, K, 0, di.GeneralCost(running, final, PARAMS, time_dependent=True),
                   n_controls=2, time_dependent=True)
    with pytest.raises(ValueError, match=r"cost.running\(x, u\) failed"):
        di.Problem(lambda x, u, ud: x, jnp.zeros(4), DT, K, 0, di.GeneralCost(running, final, PARAMS), n_controls=2)
    with pytest.raises(TypeError, match="time_dependent must be True or False; got 'yes'"):
        di.GeneralCost(running, final, PARAMS, time_dependent="yes")
    with pytest.raises(TypeError, match="needs the time t"):
        di.GeneralCost(running, final, PARAMS, time_dependent=True).running(jnp.zeros(4), jnp.zeros(2))
    assert via_problem(0).replace(x0=jnp.ones(4)).time_dependent


@pytest.mark.parametrize("delay_steps", [1, 3])
def test_time_varying_lq_equals_the_dense_optimum(delay_steps):
    """A linear plant with time-varying A(t), B(t) and drift g(t), and a cost tracking a moving
    reference r(t): the problem is an LQ problem, so the solver's optimum must equal the dense
    least-squares solution over all commands, built here with t_k = k dt (no iteration, no library
    code). l = 1 is the smallest delay with a pending command (l = 0: the via-point test)."""
    n, d, K, dt = 3, 2, 30, 0.02
    rng = np.random.default_rng(7 + delay_steps)
    A0, A1 = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    B0, B1 = rng.normal(size=(n, d)), rng.normal(size=(n, d))
    g0 = rng.normal(size=n)
    Pw, Qw, Pf = np.diag([1.0, 0.5, 2.0]), 0.1 * np.eye(d), np.diag([5.0, 5.0, 1.0])

    def A(t): return A0 + jnp.sin(8 * t) * A1
    def B(t): return B0 + t * B1
    def g(t): return g0 * jnp.cos(5 * t)
    def ref(t): return jnp.array([jnp.sin(6 * t), t, 1.0 - t])

    def f(x, u, ud, t): return A(t) @ x + B(t) @ ud + g(t)
    def running(x, u, p, t): return (x - ref(t)) @ Pw @ (x - ref(t)) + u @ Qw @ u
    def final(x, p, t): return (x - ref(t)) @ Pf @ (x - ref(t))

    x0 = rng.normal(size=n)
    problem = di.Problem(f, x0, dt, K, delay_steps, di.GeneralCost(running, final, time_dependent=True),
                         n_controls=d, time_dependent=True)
    sol = di.solve(problem)
    assert sol.converged, sol.message

    # dense reference: x_k = Phi_k U + x_free_k (U the K d commands), then least squares
    Ak = [np.eye(n) + dt * np.asarray(A(k * dt)) for k in range(K)]
    Bk = [dt * np.asarray(B(k * dt)) for k in range(K)]
    Phi, free = [np.zeros((n, K * d))], [x0]
    for k in range(K):
        acting = np.zeros((n, K * d))
        if k >= delay_steps:
            j = k - delay_steps
            acting[:, j * d:(j + 1) * d] = Bk[k]
        Phi.append(Ak[k] @ Phi[-1] + acting)
        free.append(Ak[k] @ free[-1] + dt * np.asarray(g(k * dt)))
    rows, rhs = [], []
    for k in range(K + 1):
        W = np.linalg.cholesky(dt * Pw if k < K else Pf).T
        rows.append(W @ Phi[k])
        rhs.append(W @ (np.asarray(ref(k * dt)) - free[k]))
    Wq = np.linalg.cholesky(dt * Qw).T
    rows.append(np.kron(np.eye(K), Wq))
    rhs.append(np.zeros(K * d))
    U = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    residual = np.vstack(rows) @ U - np.concatenate(rhs)
    np.testing.assert_allclose(np.asarray(sol.u).ravel(), U, rtol=1e-8, atol=1e-9 * np.abs(U).max())
    assert float(sol.cost) == pytest.approx(float(residual @ residual), rel=1e-10)
