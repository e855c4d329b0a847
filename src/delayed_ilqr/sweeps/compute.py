"""One batch of a sweep, computed: the cells' problems solved by one ``vmap`` (or one plain solve
for a batch of one), each policy run by Monte Carlo once per seed on its plant, and the statistics
of [`delayed_ilqr.statistics`][delayed_ilqr.statistics] (one definition of a diverged trial). Only the statistics leave
this module: a batch's result is a few numbers per cell, cheap to send from a Dask worker.

Runs wherever the batch runs: this process (which must compute in float64, as everywhere in the
library), or a Dask worker, which `prepare_process` sets up.
"""
from __future__ import annotations

import dataclasses
from functools import partial
from typing import Callable, NamedTuple, Optional

import jax
import numpy as np

from .. import Options, Status
from ..experiments import designs
from ..experiments.engine import endpoint_error, solve_batch, stack, take
from ..simulate import _simulate, check_memory
from ..models.metadata import default_u_init
from ..statistics import divergence_bound, diverged_trials, sample_stats
from .grid import Batch, Cell

__all__ = ["Settings", "Variable", "VARIABLES", "compute_batch", "prepare_process"]


class Variable(NamedTuple):
    """A result variable of every cell: per cell, or per cell and seed (``per_seed``)."""
    name: str
    dtype: str
    per_seed: bool
    long_name: str
    units: str          # "endpoint" stands for the model's endpoint unit (engine.endpoint_description)


VARIABLES = (
    Variable("status", "int32", False, "solver status (delayed_ilqr.Status)", ""),
    Variable("converged", "int8", False, "1 when the solve converged", ""),
    Variable("iterations", "int32", False, "iLQG iterations", ""),
    Variable("cost", "float64", False, "cost of the nominal trajectory (eq. 2)", "1"),
    Variable("expected_cost", "float64", False, "local (linearised) prediction of E[J]: J(0) of the last LQG", "1"),
    Variable("endpoint_error", "float64", False, "endpoint error of the nominal", "endpoint"),
    Variable("mc_cost_mean", "float64", True, "Monte Carlo mean cost (trials that did not diverge)", "1"),
    Variable("mc_cost_ci_low", "float64", True, "lower end of the bootstrap 95 % interval of the mean cost", "1"),
    Variable("mc_cost_ci_high", "float64", True, "upper end of the bootstrap 95 % interval of the mean cost", "1"),
    Variable("mc_cost_median", "float64", True, "Monte Carlo median cost (diverged trials as +inf)", "1"),
    Variable("mc_diverged", "int32", True, "diverged trials (delayed_ilqr.statistics.diverged_trials)", ""),
    Variable("mc_endpoint_error_mean", "float64", True, "mean endpoint error (trials that did not diverge)",
             "endpoint"),
    Variable("mc_endpoint_error_median", "float64", True, "median endpoint error (diverged trials as +inf)",
             "endpoint"),
)


@dataclasses.dataclass(frozen=True)
class Settings:
    """What every batch of one sweep shares: the model factory, its fixed arguments, the design,
    the solver options and the Monte Carlo (seeds, trials, Euler-Maruyama sub-steps)."""
    factory: Callable
    fixed: tuple                 # ((name, value), ...): the factory's arguments that do not vary
    design: str
    options: Optional[Options]
    seeds: tuple[int, ...]
    trials: int
    substeps: int
    delay_frame: Optional[int] = None    # Problem.delay_frame of every cell (None: each its own delay)

    def problem(self, cell: Cell):
        """The plant of ``cell``: ``factory(**fixed, **cell.kwargs)``, in the sweep's delay frame."""
        problem = self.factory(**dict(self.fixed), **cell.kwargs)
        return problem if self.delay_frame is None else problem.replace(delay_frame=self.delay_frame)


def prepare_process(cache_dir=None, cache: bool = True) -> None:
    """Sets up a worker process of its own, before its first JAX computation: float64, XLA's CPU
    flags ([`configure_cpu`][delayed_ilqr.configure_cpu]) and, unless ``cache`` is False, the persistent
    compilation cache ([`enable_compilation_cache`][delayed_ilqr.enable_compilation_cache]), so that a worker reads
    the solvers another process compiled."""
    from .._cache import enable_compilation_cache
    from .._cpu import configure_cpu
    configure_cpu()
    jax.config.update("jax_enable_x64", True)
    if cache:
        enable_compilation_cache(cache_dir)


def compute_batch(settings: Settings, batch: Batch, plants=None) -> list[tuple[tuple[int, ...], dict]]:
    """The batch's cells with their results: [(cell index, {variable name: value})], a value
    a scalar or, for a per-seed variable, an array [len(seeds)]. ``plants``: the cells' problems
    when already built (else built here, on the worker, from the factory)."""
    if plants is None:
        plants = [settings.problem(cell) for cell in batch.cells]
    made = [designs.design(p, settings.design, settings.options) for p in plants]
    problems, options = [m[0] for m in made], made[0][1]
    u_init = default_u_init(problems[0])
    padded = plants + [plants[-1]] * (batch.size - len(plants))
    if batch.size == 1:
        from .. import solve
        solved = jax.tree_util.tree_map(lambda a: np.asarray(a)[None], solve(problems[0], u_init, options))
    else:
        padded_designs = problems + [problems[-1]] * (batch.size - len(problems))
        solved = jax.tree_util.tree_map(np.asarray, solve_batch(padded_designs, options, u_init))  # one transfer
    stacked_plants = stack(padded)
    check_memory(plants[0], settings.trials, settings.substeps, what="trials", runs=batch.size)
    monte_carlo = [_monte_carlo(stacked_plants, solved.policy, settings.trials, settings.substeps,
                                jax.random.PRNGKey(seed)) for seed in settings.seeds]
    return [(cell.index, _cell_results(plant, take(solved, j), [(c[j], x[j]) for c, x in monte_carlo]))
            for j, (cell, plant) in enumerate(zip(batch.cells, plants))]


@partial(jax.jit, static_argnames=("n_trials", "substeps"))
def _monte_carlo(plants, policies, n_trials: int, substeps: int, key):
    """``simulate`` of each (plant, policy) pair of a batch with the same key, one after another in
    one compiled loop (as the solver's batching rule): per cell the same computation, and the same
    numbers, as ``simulate(plant, policy, n_trials, seed)``. Returns costs [B, N], final states [B, N, n]."""
    def one(pair):
        runs = _simulate(pair[0], pair[1], n_trials, substeps, key)
        return runs.cost, runs.x[:, -1]
    return jax.lax.map(one, (plants, policies))


def _cell_results(plant, sol, monte_carlo) -> dict:
    """A cell's values from its solution and, per seed, its trials' (costs [N], final states [N, n])."""
    status = Status(int(sol.status))
    out = dict(status=np.int32(status), converged=np.int8(status.converged), iterations=np.int32(sol.iterations),
               cost=np.float64(sol.cost), expected_cost=np.float64(sol.expected_cost),
               endpoint_error=np.float64(endpoint_error(plant, np.asarray(sol.x)[-1][None])[0]))
    bound = divergence_bound(plant)
    per_seed = {v.name: [] for v in VARIABLES if v.per_seed}
    for costs, finals in monte_carlo:
        diverged = diverged_trials(costs, bound)
        cost, error = sample_stats(costs, diverged), sample_stats(endpoint_error(plant, finals), diverged)
        for name, value in (("mc_cost_mean", cost.mean), ("mc_cost_ci_low", cost.ci95[0]),
                            ("mc_cost_ci_high", cost.ci95[1]), ("mc_cost_median", cost.median),
                            ("mc_diverged", cost.n_diverged), ("mc_endpoint_error_mean", error.mean),
                            ("mc_endpoint_error_median", error.median)):
            per_seed[name].append(value)
    dtypes = {v.name: v.dtype for v in VARIABLES}
    out.update({name: np.asarray(values, dtypes[name]) for name, values in per_seed.items()})
    return out
