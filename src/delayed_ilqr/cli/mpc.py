"""The ``mpc`` command: the receding-horizon controller's compensations of the delay, in closed loop
against a plant whose delay and actuators may differ from the model's."""
from __future__ import annotations

import json
import math

import click
import numpy as np

from .._files import savez, write_text
from ..experiments.delay_text import delay_text
from ..experiments.records import problem_record
from .arguments import (SEED, ModelType, OneDelay, build_problem, factory_kwargs, model_options, noise_option,
                        noise_value)
from .output import Output, kwargs_settings, out_option

COMPENSATIONS = ("none", "predict", "replay", "inflight")


@click.command("mpc")
@click.argument("model", type=ModelType(), metavar="MODEL")
@click.option("--delay", type=OneDelay(), default=0.0, show_default=True,
              help="The model's actuation delay in seconds (a whole number of the model's time steps).")
@click.option("--true-delay", type=OneDelay(), default=None,
              help="The plant's actuation delay in seconds [default: --delay].")
@click.option("--mismatch", type=click.FloatRange(min=-0.9, max=10.0), default=0.0, show_default=True,
              help="The plant's actuators deliver (1 + MISMATCH) times the command, e.g. 0.2 or -0.2.")
@click.option("--compensation", "compensations", type=click.Choice(COMPENSATIONS), multiple=True,
              help="A controller to run (repeatable) [default: all four].")
@click.option("--horizon", type=click.IntRange(min=1), default=None,
              help="The receding horizon in steps [default: the model's].")
@click.option("--ticks", type=click.IntRange(min=1), default=200, show_default=True, help="Ticks to run.")
@click.option("--iterations", type=click.IntRange(min=1), default=1, show_default=True,
              help="Solver iterations per tick (1: real-time iteration).")
@click.option("--trials", type=click.IntRange(min=1), default=1, show_default=True,
              help="Closed-loop trials (they differ only in the plant's noise).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the plant's noise.")
@noise_option
@model_options
@out_option(default=None, help="Folder for mpc.json (the table), runs.npz (states and commands) and "
                                "closed_loop.png.")
def mpc_command(model, delay, true_delay, mismatch, compensations, horizon, ticks, iterations, trials, seed, noise,
                no_noise, params, dt, out, overwrite):
    """Run MODEL's receding-horizon controller with each compensation of the delay against the plant.

    The controller plans with MODEL at --delay, without noise; the plant is MODEL at --true-delay,
    its actuators off by --mismatch, with its motor noise (--noise, on by default: for the arms
    the human preset). MODEL is one of the names that `delayed-ilqr models` lists, or your own
    factory as package.module:factory.
    """
    from ..experiments import mpc_baselines
    noise = noise_value(noise, no_noise)
    kwargs = factory_kwargs(params, dt)
    if horizon is not None:
        _check_horizon(model, horizon, delay, true_delay, kwargs)
        kwargs["horizon"] = horizon
    controller_model = build_problem(model, delay, False, kwargs)
    plant = build_problem(model, delay if true_delay is None else true_delay, noise, kwargs, hint="--true-delay")
    plant = plant.replace(dynamics=mpc_baselines.InputGain(plant.dynamics, 1.0 + mismatch), name="plant")
    chosen = compensations or COMPENSATIONS
    strategies = [s for s in mpc_baselines.STRATEGIES if s[1] in chosen and s[0] != "replay (planned)"]
    with Output(out, overwrite) as output:
        runs, rows = mpc_baselines.compare(controller_model, plant, ticks, trials, seed, iterations, strategies)
        click.echo(f"{model.name}: model delay {delay_text(controller_model)}, plant delay "
                   f"{delay_text(plant)}, actuator gain {1 + mismatch:g}, {ticks} ticks, {trials} trial(s)")
        click.echo(mpc_baselines.markdown(rows, [label for label, _, _ in strategies]))
        if out is not None:
            from ..experiments import report
            from ..plot.mpc import plot_closed_loop
            table = [{k: _json_number(v) for k, v in row._asdict().items()} for row in rows]
            write_text(output.staging / "mpc.json", json.dumps(table, indent=2, allow_nan=False) + "\n")
            savez(output.staging / "runs.npz",
                  {f"{k}_{label.replace(' ', '_')}": np.asarray(getattr(run, k)) for label, run in runs.items()
                   for k in ("x", "u", "cost", "failed")})
            report.save_figures({"closed_loop.png": plot_closed_loop(controller_model, runs)}, output.staging)
            settings = dict(model=model.name, delay=delay, true_delay=plant.delay, mismatch=mismatch,
                            compensations=list(chosen), ticks=ticks, iterations=iterations, trials=trials, seed=seed,
                            noise=plant.noise is not None, **kwargs_settings(kwargs),
                            problem=problem_record(controller_model), plant=problem_record(plant))
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")


def _json_number(value):
    """A table value for strict JSON: a NaN or infinite number becomes null."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _check_horizon(model, horizon: int, delay: float, true_delay, kwargs: dict) -> None:
    """--horizon against the model's and the plant's delays in steps (usage errors naming both)."""
    for option, seconds in (("--delay", delay), ("--true-delay", true_delay)):
        if seconds is None:
            continue
        steps = build_problem(model, seconds, False, kwargs, hint=option).delay_steps
        if steps >= horizon:
            raise click.BadParameter(f"{model.name}: the horizon must be longer than the delay (a command must act "
                                     f"within it); got --horizon {horizon} steps and {option} {seconds:g} s = {steps} "
                                     "steps", param_hint=f"'--horizon' / '{option}'")
