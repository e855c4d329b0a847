"""The ``models``, ``solve`` and ``simulate`` commands: one model, one delay."""
from __future__ import annotations

import sys

import click
import numpy as np

from .. import Options, Status
from ..experiments import delay_study, engine, report, tables
from ..models import REGISTRY
from ..models.metadata import default_u_init
from ..experiments.records import problem_record
from ..experiments.progress import progress_bar
from .arguments import (SEED, ModelType, OneDelay, build_problem, check_trials, factory_kwargs, model_options,
                        noise_option, noise_value, progress_option, substeps_option)
from .output import Output, kwargs_settings, out_option, study_settings, warn_not_converged


@click.command("models")
def models_command():
    """List the built-in models with their descriptions."""
    width = max(len(name) for name in REGISTRY)
    for name, info in REGISTRY.items():
        click.echo(f"{name.ljust(width)}  {info.description}")


@click.command("solve")
@click.argument("model", type=ModelType(), metavar="MODEL")
@click.option("--delay", type=OneDelay(), default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@noise_option
@click.option("--method", type=click.Choice(["structured", "augmented"]), default="structured", show_default=True,
              help="Backward pass: Theorem 1's structured recursion, or the state-augmentation reference.")
@model_options
@progress_option
@out_option(default=None, help="Folder for solution.json, solution.npz (the Solution, for delayed_ilqr.load) "
                                "and figures.")
def solve_command(model, delay, noise, no_noise, method, params, dt, progress, out, overwrite):
    """Solve MODEL with iLQG and report the nominal solution and its convergence.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)).
    """
    kwargs = factory_kwargs(params, dt)
    noise = noise_value(noise, no_noise)
    problem = build_problem(model, delay, noise, kwargs)
    with Output(out, overwrite) as output:
        # one step, but the first solve of a process compiles for seconds: the bar shows the time
        with progress_bar(1, f"solve {model.name}", "solve", progress) as bar:
            timed = engine.timed_solve(problem, Options(method=method), default_u_init(problem))
            bar.update()
        sol = timed[0]
        label, unit = engine.endpoint_description(problem)
        endpoint = (label, unit, engine.endpoint_error(problem, np.asarray(sol.x[-1])[None])[0])
        click.echo(tables.pairs(tables.solve_summary(problem, model.description, problem.noise is not None, method,
                                                     timed, endpoint)))
        if out is not None:
            from .. import plot
            report.write_solution(output.staging, model.name, problem, method, timed, endpoint)
            report.save_figures({"trajectories.png": plot.plot_trajectories(problem, sol),
                                 "convergence.png": plot.plot_convergence({model.name: sol})}, output.staging)
            written = output.commit(dict(model=model.name, delay=delay, noise=problem.noise is not None,
                                         method=method, **kwargs_settings(kwargs), problem=problem_record(problem)))
            click.echo(f"wrote {', '.join(written)} to {out}")
    status = Status(int(sol.status))
    if not status.converged:
        click.echo(f"error: the solve did not converge ({status.name}): {status.message}", err=True)
        sys.exit(1)


@click.command("simulate")
@click.argument("model", type=ModelType(), metavar="MODEL")
@click.option("--delay", type=OneDelay(), default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Number of Monte Carlo trials (a positive integer).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise (the same seed gives the same trials).")
@noise_option
@click.option("--controller", type=click.Choice(sorted(delay_study.CONTROLLERS)), default="aware", show_default=True,
              help="aware: designed with the delay; ignorant: designed for no delay and run on the delayed "
                   "plant; augmented: delay-aware by state augmentation.")
@substeps_option
@model_options
@progress_option
@out_option(default=None, help="Folder for simulate.json (summary), runs.npz (trials, nominal, gains), "
                                "solution.npz (for delayed_ilqr.load) and figures.")
def simulate_command(model, delay, trials, seed, noise, no_noise, controller, substeps, params, dt, progress, out,
                     overwrite):
    """Solve MODEL and run its feedback policy on the (noisy, delayed) plant --trials times.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)).
    """
    kwargs = factory_kwargs(params, dt)
    problem = build_problem(model, delay, noise_value(noise, no_noise), kwargs)
    check_trials(problem, trials, substeps)
    with Output(out, overwrite) as output:
        with progress_bar(1, f"simulate {model.name}", "design and Monte Carlo", progress) as bar:
            r = delay_study.evaluate(problem, controller, trials, seed, substeps=substeps)
            bar.update()
        click.echo(tables.pairs(tables.simulate_summary(r, model.description)))
        if out is not None:
            from .. import plot
            settings = dict(study_settings(model.name, problem.noise is not None, trials, seed, substeps),
                            delay=problem_record(problem)["delay"], controller=controller, **kwargs_settings(kwargs),
                            problem=problem_record(problem))
            report.write_runs(output.staging, r, settings)
            figures = {"trajectories.png": plot.plot_trajectories(problem, r.solution, r.runs)}
            if plot.draws_paths(problem):
                figures["hand_paths.png"] = plot.plot_hand_paths([r])
            report.save_figures(figures, output.staging)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    if warn_not_converged([r]):
        sys.exit(1)
