"""Inverse optimal control: fit a model's cost weights and noise level to measured reaches by
gradient-based minimisation through the solver, and its delay by a profile over whole steps
(``docs/fitting.md``).

The data of one condition c (a reach target, say) are the mean task-space path m_c [K+1, m] of the
trials and the covariance C_c [m, m] of their endpoints. The model with parameters theta predicts
both from its optimal policy ([`delayed_ilqr.prediction`][delayed_ilqr.prediction]: the nominal's path and the exact
second moments of the linearised closed loop), and the fit minimises

    loss(theta) = sum_c  |m_c - m_c(theta)|^2 / ((K+1) s^2)  +  KL(C_c, C_c(theta))
    KL(C, C')   = (tr(C'^{-1} C) - m + log det C' - log det C) / 2

(KL: the divergence of the Gaussian N(0, C') from N(0, C), zero only where C' = C, and blind to
the units of the task space; s, ``mean_scale``, is the precision of a mean path, e.g. its standard
error) by SciPy's L-BFGS-B over log theta, the gradient by reverse mode through
[`delayed_ilqr.solve`][delayed_ilqr.solve] (implicit differentiation, ``docs/derivation.md`` §16). All conditions
are solved in one vectorised call.

Only ratios of the cost weights are identifiable from behaviour: scaling every weight by one factor
leaves the optimal policy, and so every prediction, unchanged. Fix one weight (the examples fix the
final position weight w_p) and fit the others relative to it.

The delay is a whole number of steps, a static size of the problem: [`profile_delay`][delayed_ilqr.experiments.fitting.profile_delay] fits
theta at each candidate delay (one compilation each) and takes the delay of the smallest loss.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import Options, Problem, Runs, Status, _files, _validate, solve
from ..models.metadata import default_u_init, task_space
from ..prediction import predict, task_prediction
from .progress import progress_bar

__all__ = ["ReachData", "Fit", "AtDelay", "Evaluator", "predicted_reach", "observed_reach", "reach_loss", "fit",
           "profile_delay", "check_reach_data", "save_reach_data", "load_reach_data"]


class ReachData(NamedTuple):
    """Reach statistics of C conditions.

    Attributes:
        mean: [C, K+1, m] mean task-space path.
        endpoint_cov: [C, m, m] covariance of the final task-space position.
    """

    mean: jax.Array
    endpoint_cov: jax.Array


class Fit(NamedTuple):
    """The outcome of [`fit`][delayed_ilqr.experiments.fitting.fit].

    Attributes:
        params: the fitted parameters, by name (floats).
        loss: the loss at ``params`` (inf where a solve there did not converge).
        converged: L-BFGS-B met its tolerance and every solve at ``params`` converged.
        message: L-BFGS-B's message, and the statuses of unconverged solves if any.
        iterations: L-BFGS-B iterations; evaluations: loss and gradient evaluations (each one
            vectorised solve and its gradient).
    """

    params: dict
    loss: float
    converged: bool
    message: str
    iterations: int
    evaluations: int


def predicted_reach(problem: Problem, solution) -> tuple:
    """(mean task-space path [K+1, m], endpoint covariance [m, m]) that ``solution`` predicts on
    ``problem`` ([`delayed_ilqr.prediction.task_prediction`][delayed_ilqr.prediction.task_prediction]); differentiable."""
    task = task_prediction(problem, predict(problem, solution))
    return task.mean, task.cov[-1]


def observed_reach(problem: Problem, runs: Runs) -> tuple:
    """(mean task-space path [K+1, m], endpoint covariance [m, m], ddof = 1) of Monte Carlo
    ``runs`` on ``problem`` (all trials: a diverged one shows as an outlier, not silently dropped)."""
    task = task_space(problem)
    if task is None:
        raise ValueError(f"observed_reach: problem {problem.name!r} has no task space (metadata.task is None)")
    paths = np.asarray(task.map(jnp.asarray(runs.x)))                       # [N, K+1, m]
    return paths.mean(axis=0), np.cov(paths[:, -1], rowvar=False)


def reach_loss(mean, cov, data_mean, data_cov, mean_scale):
    """One condition's term of the loss (module docstring): predicted ``mean`` [K+1, m] and
    endpoint ``cov`` [m, m] against the data's."""
    m = cov.shape[-1]
    path = jnp.sum((mean - data_mean) ** 2) / (mean.shape[0] * mean_scale ** 2)
    chol = jnp.linalg.cholesky(cov)
    solved = jax.scipy.linalg.cho_solve((chol, True), data_cov)
    kl = 0.5 * (jnp.trace(solved) - m + 2 * jnp.sum(jnp.log(jnp.diag(chol))) - jnp.linalg.slogdet(data_cov)[1])
    return path + kl


def _total(log_params, u_init, conditions, data: ReachData, mean_scale, delay_steps, make_problem, options):
    """The loss at theta = exp(log_params) (dict), every condition in one vmap, and the statuses [C]
    of its solves, started from ``u_init`` [C, K, d]; ``delay_steps``: None, or the delay (data)
    of ``make_problem``'s framed problems."""
    params = {k: jnp.exp(v) for k, v in log_params.items()}

    def one(condition, start, data_mean, data_cov):
        problem = make_problem(params, condition)
        if delay_steps is not None:
            problem = problem.replace(delay_steps=delay_steps)
        sol = solve(problem, start, options)
        mean, cov = predicted_reach(problem, sol)
        return reach_loss(mean, cov, data_mean, data_cov, mean_scale), sol.status

    losses, aux = jax.vmap(one)(conditions, u_init, data.mean, data.endpoint_cov)
    return jnp.sum(losses), aux


# module level with make_problem static: fits with the same model function (e.g. from exact and
# from sampled data, or a profile's fit again at its best delay) share one compilation
_value_and_grad = jax.jit(jax.value_and_grad(_total, has_aux=True), static_argnames=("make_problem",))


@dataclass(frozen=True)
class AtDelay:
    """``make_problem(params, condition, delay)`` at a fixed delay (seconds), as [`fit`][delayed_ilqr.experiments.fitting.fit] takes
    it; equal (and hashed) by value, so that fits at the same delay share a compilation. With
    ``delay_frame`` L its problems get that frame ([`profile_delay`][delayed_ilqr.experiments.fitting.profile_delay]: the fits of every delay
    then share one compilation, each passing its own delay to [`fit`][delayed_ilqr.experiments.fitting.fit] as data)."""

    make_problem: Callable
    delay: float
    delay_frame: Optional[int] = None

    def __call__(self, params, condition):
        problem = self.make_problem(params, condition, self.delay)
        return problem if self.delay_frame is None else problem.replace(delay_frame=self.delay_frame)


class Evaluator:
    """The loss of [`fit`][delayed_ilqr.experiments.fitting.fit] and its gradient at given parameters, through the compiled
    program that every fit of the same model shares (a coarse search before a fit reuses it).

    Args:
        make_problem: as for [`fit`][delayed_ilqr.experiments.fitting.fit].
        conditions: as for `fit`.
        data: as for `fit`.
        params0: positive floats by name: the first condition's problem at these values is the
            one ``data`` are checked against.
        u_init: as for `fit`.
        mean_scale: as for `fit`.
        options: as for `fit`.
        delay_steps: as for `fit`.

    Calling it with ``params`` (a dict of positive floats, the same names) returns (the loss, its
    gradient in log theta by name, the statuses [C] of the solves), all NumPy; the loss is inf
    where a solve did not converge or a predicted covariance is not positive definite.

    Raises:
        ValueError: naming the argument, for a non-positive ``mean_scale`` and for data that do
            not fit the model ([`check_reach_data`][delayed_ilqr.experiments.fitting.check_reach_data]).
    """

    def __init__(self, make_problem, conditions, data: ReachData, params0: dict, u_init=None,
                 mean_scale: float = 1e-3, options: Optional[Options] = None, delay_steps: Optional[int] = None):
        if not (np.isfinite(mean_scale) and mean_scale > 0):
            raise ValueError(f"mean_scale must be a positive float; got {mean_scale!r}")
        count = len(jax.tree_util.tree_leaves(conditions)[0])
        first = make_problem({k: float(v) for k, v in params0.items()},
                             jax.tree_util.tree_map(lambda a: a[0], conditions))
        self.data = check_reach_data(first, count, data)
        if u_init is None:
            u_init = default_u_init(first)
            u_init = jnp.zeros((first.horizon, first.n_controls)) if u_init is None else u_init
        # every evaluation solves from the same u_init: a warm start from the previous evaluation's
        # solution made the loss depend on the path of the fit (a solve stops anywhere within its
        # tolerance, and the muscle arm's solves from different starts stop at different commands)
        self.u_init = jnp.broadcast_to(jnp.asarray(u_init), (count,) + np.shape(u_init))
        self.make_problem, self.conditions, self.mean_scale = make_problem, conditions, mean_scale
        self.options = Options() if options is None else options
        self.delay = None if delay_steps is None else jnp.asarray(_validate.delay_steps(delay_steps), jnp.int32)

    def __call__(self, params: dict) -> tuple:
        return self.at_log({k: np.log(float(v)) for k, v in params.items()})

    def at_log(self, log_params: dict) -> tuple:
        """As a call, at theta = exp(log_params) (log theta by name, the variables of the fit)."""
        log_params = {k: jnp.asarray(v) for k, v in log_params.items()}
        (value, status), grad = _value_and_grad(log_params, self.u_init, self.conditions, self.data, self.mean_scale,
                                                self.delay, make_problem=self.make_problem, options=self.options)
        return float(value), {k: float(g) for k, g in grad.items()}, np.asarray(status)


def fit(make_problem: Callable[[dict, object], Problem], conditions, data: ReachData, params0: dict,
        u_init=None, mean_scale: float = 1e-3, options: Optional[Options] = None, gtol: float = 1e-8,
        ftol: float = 0.0, max_iterations: int = 100, delay_steps: Optional[int] = None,
        on_evaluation: Optional[Callable[[int, float], None]] = None, bounds: Optional[dict] = None) -> Fit:
    """Fits positive parameters theta to reach data by L-BFGS-B on log theta (module docstring).

    Args:
        make_problem: ``make_problem(params, condition) -> Problem``; ``params`` maps each name of
            ``params0`` to a traced scalar, ``condition`` is one slice of ``conditions``. Every
            condition's problem must have the same shapes (delay, horizon).
        conditions: a pytree of arrays with a leading axis C (e.g. targets [C, 2]).
        data: the [`ReachData`][delayed_ilqr.experiments.fitting.ReachData] of the C conditions, in the same order.
        params0: the starting values (positive floats), by name.
        u_init: [K, d] initial commands of every solve; default the model's
            ([`default_u_init`][delayed_ilqr.models.metadata.default_u_init]).
        mean_scale: s, the precision of the mean paths in task units (e.g. their standard error).
        options: the solver's [`Options`][delayed_ilqr.Options].
        gtol: L-BFGS-B's tolerance on the projected gradient of the loss in log theta.
        ftol: L-BFGS-B's tolerance on the relative decrease of the loss in one iteration (0:
            none). A loss whose solves stop within a tolerance is rough at its smallest scales,
            and near its minimum the line search can fail there for many evaluations before
            L-BFGS-B gives up; a small ftol (1e-7, say) ends the fit when the steps stop paying.
        max_iterations: L-BFGS-B's iteration limit.
        delay_steps: None, or the delay in steps at which to fit when ``make_problem``'s problems
            have a ``delay_frame``: it replaces their delay and reaches the compiled loss as
            data, so fits at different delays share one compilation ([`profile_delay`][delayed_ilqr.experiments.fitting.profile_delay]).
        on_evaluation: optional ``on_evaluation(count, loss)`` after each evaluation of the loss
            (a progress display).
        bounds: optional ``{name: (low, high)}``, positive limits (or None) on some parameters,
            which L-BFGS-B keeps (a fitted delay below its frame's longest, say).

    Returns:
        A [`Fit`][delayed_ilqr.experiments.fitting.Fit]. An evaluation where a solve did not converge counts as an infinite loss
        (its gradient is NaN, ``docs/derivation.md`` §16), so the line search steps back; a fit
        whose final loss is not finite has not converged.

    Raises:
        ValueError: naming the argument, for non-positive starting values or ``mean_scale``, and
            for data that do not fit the model ([`check_reach_data`][delayed_ilqr.experiments.fitting.check_reach_data]).
    """
    from scipy.optimize import minimize

    names = sorted(params0)
    values = np.array([float(params0[k]) for k in names])
    if not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(f"params0 must map names to positive finite floats; got {params0!r}")
    evaluate = Evaluator(make_problem, conditions, data, dict(zip(names, values)), u_init, mean_scale, options,
                         delay_steps)
    last = {}

    def value_and_grad(log_values):
        value, grad, status = evaluate.at_log(dict(zip(names, log_values)))
        grad = np.array([grad[k] for k in names])
        last.update(status=status, count=last.get("count", 0) + 1)
        if on_evaluation is not None:
            on_evaluation(last["count"], value)
        if not (np.isfinite(value) and np.all(np.isfinite(grad))):
            return np.inf, np.zeros_like(grad)
        return value, grad

    limits = [tuple(None if b is None else float(np.log(b)) for b in (bounds or {}).get(k, (None, None)))
              for k in names]
    result = minimize(value_and_grad, np.log(values), jac=True, method="L-BFGS-B", bounds=limits,
                      options=dict(gtol=gtol, ftol=ftol, maxiter=max_iterations))
    value, _ = value_and_grad(result.x)
    unconverged = [Status(int(s)).name for s in last["status"] if not Status(int(s)).converged]
    message = str(result.message) + (f"; unconverged solves: {unconverged}" if unconverged else "")
    # an infinite loss (a prediction without spread, or a solve that failed) has a zero gradient
    # here, on which L-BFGS-B stops at once and reports success
    finite = bool(np.isfinite(value))
    if not finite:
        message += "; the loss is not finite at the returned parameters (a predicted endpoint covariance that " \
                   "is not positive definite, or a solve that did not converge)"
    return Fit(dict(zip(names, np.exp(result.x).tolist())), float(value),
               bool(result.success) and not unconverged and finite, message, int(result.nit), int(result.nfev))


def check_reach_data(problem: Problem, count: int, data: ReachData) -> ReachData:
    """``data`` as float64 arrays, checked against ``count`` conditions of ``problem``'s shape.

    Raises:
        ValueError: naming the array, the rule and what was received, unless ``data.mean`` is a
            finite [C, K+1, m] array (m the task space's dimension) and ``data.endpoint_cov`` C
            symmetric positive definite [m, m] matrices (the KL term of a singular or indefinite
            one is infinite or negative).
    """
    if not isinstance(data, ReachData):
        raise TypeError(f"data must be a fitting.ReachData(mean, endpoint_cov); got {type(data).__name__}")
    task = task_space(problem)
    if task is None:
        raise ValueError(f"fit: problem {problem.name!r} has no task space (metadata.task is None), so reach data "
                         "cannot be compared with it")
    m = jax.eval_shape(task.map, jax.ShapeDtypeStruct((problem.n_states,), jnp.float64)).shape[-1]
    K = problem.horizon
    mean = np.asarray(data.mean, dtype=np.float64)
    cov = np.asarray(data.endpoint_cov, dtype=np.float64)
    if mean.shape != (count, K + 1, m):
        raise ValueError(f"data.mean must have shape (C={count}, K+1={K + 1}, m={m}): one mean task-space path "
                         f"per condition over the horizon of the model; got shape {mean.shape}")
    if cov.shape != (count, m, m):
        raise ValueError(f"data.endpoint_cov must have shape (C={count}, m={m}, m={m}): one endpoint covariance "
                         f"per condition in the model's task space; got shape {cov.shape}")
    for name, a in (("data.mean", mean), ("data.endpoint_cov", cov)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite; got {int(np.sum(~np.isfinite(a)))} non-finite values")
    for c in range(count):
        _validate.symmetric_psd(cov[c], f"data.endpoint_cov[{c}]", definite=True)
    return ReachData(jnp.asarray(mean), jnp.asarray(cov))


def profile_delay(make_problem: Callable[[dict, object, float], Problem], delays: Sequence[float], conditions,
                  data: ReachData, params0: dict, delay_frame: bool = True, progress: bool = False,
                  **kwargs) -> tuple:
    """Fits theta at each candidate delay ([`fit`][delayed_ilqr.experiments.fitting.fit]; ``make_problem(params, condition, delay)``,
    the delay in seconds) and returns (the delay of the smallest final loss, [Fit per delay]).

    With ``delay_frame`` (the default) the problems are built at the longest delay and put in a
    frame of its steps (``Problem.delay_frame``), and each fit passes its delay as data: the fits
    share one compilation of the loss and its gradient instead of one per delay (their results
    equal the unframed fits' to round-off). That needs ``make_problem`` to depend on the delay
    only through ``delay_steps``; where it does not (the problems at two delays differ in more
    than the delay), or with sensors, each delay compiles its own. ``progress``: a bar on stderr
    over the delays, with the current fit's evaluations and loss (when stderr is a terminal).
    """
    fits = None
    with progress_bar(len(delays), "fit", "delay", progress) as bar:
        def counted(problem_at, **more):
            shown = lambda n, loss: bar.set_postfix_str(f"evaluation {n}, loss {loss:.4g}")  # noqa: E731
            result = fit(problem_at, conditions, data, params0, on_evaluation=shown, **more, **kwargs)
            bar.update()
            return result

        if delay_frame:
            frame = _common_frame(make_problem, delays, conditions, params0)
            if frame is not None:
                longest, steps = frame
                at = AtDelay(make_problem, longest, max(steps))
                fits = [counted(at, delay_steps=l) for l in steps]
        if fits is None:
            fits = [counted(AtDelay(make_problem, float(delay))) for delay in delays]
    # the loss, not Fit.converged: L-BFGS-B often ends a fit on a rough loss with an abnormal line
    # search; a fit whose final solves did not converge has an infinite loss
    losses = [f.loss for f in fits]
    return delays[int(np.argmin(losses))], fits


def _common_frame(make_problem, delays: Sequence[float], conditions, params0: dict):
    """(the longest delay, [delay steps per candidate]) when ``make_problem``'s problems of every
    candidate delay equal the longest delay's but for ``delay_steps`` (static parts and arrays, at
    theta0 and the first condition) and have no sensors; else None."""
    condition = jax.tree_util.tree_map(lambda a: a[0], conditions)
    params = {k: float(v) for k, v in params0.items()}
    problems = [make_problem(params, condition, float(delay)) for delay in delays]
    longest = max(range(len(delays)), key=lambda i: problems[i].delay_steps)
    frame = problems[longest].delay_steps
    if any(p.observation is not None for p in problems):
        return None
    reference = problems[longest].replace(delay_frame=frame)
    ref_leaves, ref_tree = jax.tree_util.tree_flatten(reference)
    for p in problems:
        leaves, tree = jax.tree_util.tree_flatten(p.replace(delay_frame=frame, delay_steps=frame))
        if tree != ref_tree or not all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(leaves, ref_leaves)):
            return None
    return float(delays[longest]), [int(p.delay_steps) for p in problems]


#: The arrays of a data file ([`save_reach_data`][delayed_ilqr.experiments.fitting.save_reach_data]), by name.
DATA_ARRAYS = ("conditions", "mean", "endpoint_cov")


def save_reach_data(path, conditions, data: ReachData) -> None:
    """Writes the data of C conditions, atomically, as the NPZ file ``path`` (that name) that
    [`load_reach_data`][delayed_ilqr.experiments.fitting.load_reach_data] and ``delayed-ilqr fit`` read: ``conditions`` [C, ...] (e.g. the
    targets), ``mean`` [C, K+1, m] and ``endpoint_cov`` [C, m, m] (e.g. from
    [`observed_reach`][delayed_ilqr.experiments.fitting.observed_reach] of each condition's trials)."""
    _files.savez(path, dict(conditions=np.asarray(conditions), mean=np.asarray(data.mean),
                            endpoint_cov=np.asarray(data.endpoint_cov)))


def load_reach_data(path) -> tuple:
    """(conditions [C, ...], [`ReachData`][delayed_ilqr.experiments.fitting.ReachData]) from a file of [`save_reach_data`][delayed_ilqr.experiments.fitting.save_reach_data].

    Raises:
        ValueError: naming the file and the array, when an array is missing, the shapes do not
            agree on C and m, or a value is not finite.
    """
    what = f"an NPZ file of the arrays {', '.join(DATA_ARRAYS)} (save_reach_data writes one)"
    with _files.open_npz(path, what) as f:
        missing = [name for name in DATA_ARRAYS if name not in f.files]
        if missing:
            raise _files.FileFormatError(path, f"must hold the arrays {', '.join(DATA_ARRAYS)}; missing "
                                               f"{', '.join(missing)}")
        arrays = [_files.read_entry(f, name, path, what) for name in DATA_ARRAYS]
    if any(a.dtype.kind not in "biuf" for a in arrays):
        raise _files.FileFormatError(path, f"{', '.join(DATA_ARRAYS)} must be numbers; got dtypes "
                                           f"{[str(a.dtype) for a in arrays]}")
    conditions, mean, cov = (np.asarray(a, dtype=np.float64) for a in arrays)
    count = len(conditions) if conditions.ndim else 0
    if count == 0:
        raise ValueError(f"{path}: conditions must have a leading axis C >= 1; got shape {conditions.shape}")
    if mean.ndim != 3 or mean.shape[0] != count:
        raise ValueError(f"{path}: mean must be [C={count}, K+1, m] (mean paths); got shape {mean.shape}")
    if cov.shape != (count, mean.shape[2], mean.shape[2]):
        raise ValueError(f"{path}: endpoint_cov must be [C={count}, m={mean.shape[2]}, m] (endpoint covariances); "
                         f"got shape {cov.shape}")
    for name, a in zip(DATA_ARRAYS, (conditions, mean, cov)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: {name} must be finite; got {int(np.sum(~np.isfinite(a)))} non-finite values")
    return jnp.asarray(conditions), ReachData(jnp.asarray(mean), jnp.asarray(cov))
