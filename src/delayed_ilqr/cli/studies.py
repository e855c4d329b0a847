"""The study commands: ``compare`` (delay-aware against delay-ignorant control at several delays),
``demo`` (that study on the arm, with its report), ``center-out`` (the six-muscle arm's reaches to
a circle of targets) and ``perturb`` (a kick mid-reach against the sensory delay)."""
from __future__ import annotations

import dataclasses
import math
import pathlib
import sys
import time

import click
import numpy as np

from .._files import savez, write_text
from ..experiments import center_out, delay_study, perturbation, report, tables
from ..models import REGISTRY, arm2_muscle6
from ..experiments.delay_text import delay_text
from ..experiments.records import problem_record
from .arguments import (SEED, DelayFrame, DelayList, Model, ModelType, build_problem, check_trials, factory_kwargs,
                        model_options, noise_option, noise_value, progress_option, substeps_option)
from ..statistics import divergence_bound, diverged_trials, prediction_warning, sample_stats
from .output import Output, kwargs_settings, out_option, study_settings, warn_not_converged

DEMO_DELAYS = (0.0, 0.05, 0.1, 0.15)


def _check_study(model, delays, trials, noise, controllers, substeps, kwargs=None) -> list:
    """Every delay and the memory of all the trials, checked before anything is solved; returns
    the problems."""
    problems = [build_problem(model, tau, noise, kwargs, hint="--delays") for tau in delays]
    check_trials(problems[-1], trials, substeps, runs=len(delays) * len(controllers))
    return problems


def _run_study(model, delays, trials, seed, noise, controllers, substeps, model_kwargs=None, delay_frame="none",
               progress=True):
    model = model.factory if isinstance(model, Model) else model
    return delay_study.compare_delays(model, delays, trials, seed, noise=noise, controllers=controllers,
                                      substeps=substeps, model_kwargs=model_kwargs, progress=progress,
                                      delay_frame=None if delay_frame == "none" else delay_frame)


def _study_outputs(results, out: pathlib.Path, settings: dict, stem: str) -> list[str]:
    """Writes the JSON records, the NPZ of all trials and gains, and the figures; returns file names."""
    from .. import plot
    written = report.write_delay_study(results, out, settings, stem)
    return written + report.save_figures(plot.delay_study_figures(results), out)


@click.command("compare")
@click.argument("model", type=ModelType(), metavar="MODEL")
@click.option("--delays", type=DelayList(), default="0,0.05,0.1", show_default=True,
              help="Comma-separated input delays in seconds, each a whole number of the model's time steps.")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise; all controllers see the same noise samples.")
@noise_option
@click.option("--augmented/--no-augmented", default=False, show_default=True,
              help="Also evaluate the state-augmentation solution (delay-aware reference).")
@substeps_option
@click.option("--delay-frame", type=DelayFrame(), default="none", show_default=True,
              help="auto: the delays share one compiled solver and Monte Carlo (the delay as data, in a frame "
                   "of the longest delay; results equal to round-off, first-call times at the first delay "
                   "only); none: each delay compiles its own; N: a frame of N steps.")
@model_options
@progress_option
@out_option(default=None, help="Folder for compare.json, compare.md, compare_runs.npz and figures.")
def compare_command(model, delays, trials, seed, noise, no_noise, augmented, substeps, delay_frame, params, dt,
                    progress, out, overwrite):
    """Delay-aware vs delay-ignorant control of MODEL at several delays, by Monte Carlo.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)). Prints one table
    row per delay and controller. With --dt the delays are whole numbers of that step, e.g.
    --dt 0.005 --delays 0,0.025,0.05,0.075,0.1,0.125,0.15.
    """
    controllers = ["aware", "ignorant"] + (["augmented"] if augmented else [])
    kwargs = factory_kwargs(params, dt)
    noise = noise_value(noise, no_noise)
    problems = _check_study(model, delays, trials, noise, controllers, substeps, kwargs)
    with Output(out, overwrite) as output:
        try:
            results = _run_study(model, delays, trials, seed, noise, controllers, substeps, kwargs, delay_frame,
                                 progress)
        except ValueError as exc:       # a frame shorter than a delay
            raise click.UsageError(str(exc)) from None
        table = tables.delay_study_rows(results)
        click.echo(tables.text_table(table))
        warned = echo_warnings(tables.delay_study_warnings(results))
        if out is not None:
            settings = dict(study_settings(model.name, noise is not False, trials, seed, substeps),
                            delays=list(delays), controllers=controllers, delay_frame=delay_frame,
                            **kwargs_settings(kwargs), problems=[problem_record(p) for p in problems])
            _study_outputs(results, output.staging, settings, "compare")
            write_text(output.staging / "compare.md", tables.markdown_table(table) + "\n" + warnings_section(warned))
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    if warn_not_converged(results):
        sys.exit(1)


@click.command("demo")
@out_option(default=pathlib.Path("out"), show_default=True,
             help="Folder for the report (report.md, report.json, report_runs.npz, figures).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise.")
@progress_option
def demo_command(out, overwrite, trials, seed, progress):
    """The arm reaching study: delay-aware vs delay-ignorant iLQG on the noisy two-link arm.

    The P2 reach with signal-dependent torque noise at the human level (models.arm2(noise=True),
    the "human" preset calibrated to human force variability, docs/models.md §4.5; P2-noisy's
    sigma_u = 0.2, noise="benchmark", is a numerical stress test), input delays 0, 50, 100 and
    150 ms, --trials noisy trials per controller and delay. Prints the table and writes a markdown
    report with figures.
    """
    problems = _check_study(ModelType().convert("arm2", None, None), list(DEMO_DELAYS), trials, True,
                            ["aware", "ignorant"], 1)
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        results = _run_study("arm2", list(DEMO_DELAYS), trials, seed, True, ["aware", "ignorant"], 1,
                             progress=progress)
        elapsed = time.perf_counter() - start
        click.echo(tables.text_table(tables.delay_study_rows(results)))
        echo_warnings(tables.delay_study_warnings(results))
        settings = dict(study_settings("arm2", True, trials, seed, 1), delays=list(DEMO_DELAYS),
                        controllers=["aware", "ignorant"], elapsed_seconds=elapsed,
                        problems=[problem_record(p) for p in problems])
        _study_outputs(results, output.staging, settings, "report")
        report.write_demo_report(output.staging, results, REGISTRY["arm2"].description, DEMO_DELAYS, trials, seed,
                                 elapsed)
        written = output.commit(settings)
        click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if warn_not_converged(results):
        sys.exit(1)


@click.command("center-out")
@click.option("--delays", type=DelayList(), default=",".join(str(d) for d in DEMO_DELAYS), show_default=True,
              help="Comma-separated input delays in seconds (whole multiples of the 10 ms step).")
@click.option("--targets", "n_targets", type=click.IntRange(min=1), default=8, show_default=True,
              help="Number of targets on the circle.")
@click.option("--radius", type=click.FloatRange(min=0.0, min_open=True), default=0.1, show_default=True,
              help="Circle radius in metres around the start hand position.")
@click.option("--trials", type=click.IntRange(min=2), default=200, show_default=True,
              help="Noisy trials per target and delay.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the noise.")
@click.option("--sigma-u", type=click.FloatRange(min=0.0), default=center_out.SIGMA_U, show_default=True,
              help="Excitation noise of the plant the policies run on.")
@click.option("--design", "designs", type=click.Choice(center_out.DESIGNS), multiple=True,
              help="Controller design, repeatable: noise-aware (iLQG, made for the noisy plant), "
                   "deterministic (iLQR, made for the noise-free arm) or statistical (the noise-aware "
                   "design with its feedback re-designed by statistical linearisation; full-state "
                   "feedback only, not with --sensory-delay).  [default: "
                   f"{', '.join(center_out.DESIGNS)}; {', '.join(center_out.SENSING_DESIGNS)} with --sensory-delay]")
@click.option("--max-iterations", type=click.IntRange(min=1), default=center_out.DEFAULT_OPTIONS.max_iterations,
              show_default=True, help="Iteration limit of each reach's solve.")
@click.option("--sensory-delay", type=click.FloatRange(min=0.0), default=None,
              help="Controllers see the arm's proprioception (joint angles and velocities, with sensory noise) "
                   "this many seconds late through a delayed Kalman filter, instead of the state; a whole "
                   "number of 10 ms steps, 0 allowed.  [default: the state is seen]")
@click.option("--allow-unconverged", is_flag=True,
              help="Exit 0 even when some reaches did not converge (they are flagged in the table and on stderr).")
@progress_option
@out_option(default=None, help="Folder for center_out.md/.json and the figures.")
def center_out_command(delays, n_targets, radius, trials, seed, sigma_u, designs, max_iterations, sensory_delay,
                       allow_unconverged, progress, out, overwrite):
    """Center-out reaching with the six-muscle arm (arm2_muscle6) at several input delays.

    Per delay and design: one vectorised solve of the reaches to all targets (excitations limited
    to [0, 1]), then --trials noisy trials per target. Prints iterations, solve time, the
    nominal's final hand error, predicted and Monte Carlo costs and the endpoint spread; writes
    hand paths with endpoint ellipses and the excitation patterns per target. Exits 1 when a
    reach did not converge, unless --allow-unconverged.
    """
    try:
        for d in delays:
            arm2_muscle6(delay=d)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--delays'") from exc
    if sensory_delay is not None:
        try:
            arm2_muscle6(sensory_delay=sensory_delay)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--sensory-delay'") from exc
    try:
        designs = center_out.designs_for(designs or None, sensory_delay)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--design'") from exc
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        options = dataclasses.replace(center_out.DEFAULT_OPTIONS, max_iterations=max_iterations)
        results = center_out.center_out(delays, n_targets, radius, trials, seed, options=options, sigma_u=sigma_u,
                                        designs=designs, sensory_delay=sensory_delay, progress=progress)
        elapsed = time.perf_counter() - start
        rows = tables.center_out_rows(results)
        table = tables.markdown_table(rows)         # for center_out.md; the terminal gets aligned columns
        click.echo(tables.text_table(rows))
        warned = echo_warnings(tables.center_out_warnings(results))
        if out is not None:
            from .. import plot
            figures = report.save_figures(plot.center_out_figures(results), output.staging)
            # the problem of the first delay and target; the others differ in the delay and the target
            settings = dict(delays=list(delays), targets=n_targets, radius=radius, trials=trials, seed=seed,
                            sigma_u=sigma_u, designs=list(designs), max_iterations=max_iterations,
                            sensory_delay=sensory_delay, elapsed_seconds=elapsed,
                            problem=problem_record(results[0].plants[0]),
                            target_positions=[[float(v) for v in t.target] for t in results[0].targets])
            report.write_center_out_report(output.staging, results, settings, table + "\n" + warnings_section(warned),
                                           figures)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    failed = [(r.delay, r.design, j) for r in results for j, t in enumerate(r.targets) if not t.converged]
    for delay, design, j in failed:
        click.echo(f"warning: the {design} reach to target {j + 1} at delay {delay_text(delay)} did not converge",
                   err=True)
    if failed and not allow_unconverged:
        sys.exit(1)


def _perturb_rows(results) -> list[dict]:
    """One table row per sensory delay: design, the local prediction and the Monte Carlo cost
    (mean [95 % CI], median) unperturbed and kicked, and the latencies after the kick."""
    rows = []
    for r in results:
        dt, kp = r.problem.dt, r.pulse_step
        after = lambda k: None if k is None else 1000 * dt * (k - kp)          # noqa: E731
        bound = divergence_bound(r.problem)
        stats = [sample_stats(np.asarray(runs.cost), diverged_trials(np.asarray(runs.cost), bound))
                 for runs in (r.base, r.perturbed)]
        rows.append({"sensory delay [ms]": 1000 * r.sensory_delay, "status": str(r.solution.status),
                     tables.PREDICTED: float(r.solution.expected_cost), **tables.mc_record(stats[0]),
                     **{k.replace("MC J", "MC J kicked"): v for k, v in tables.mc_record(stats[1]).items()
                        if k != "diverged"},
                     "first response [ms after kick]": after(r.latency_steps),
                     "half-peak response [ms after kick]": after(r.half_steps)})
    return rows


def _perturb_warnings(rows) -> list[str]:
    lines = [prediction_warning(f"unperturbed trials at sensory delay {row['sensory delay [ms]']:g} ms",
                                math.nan if row["MC J mean"] is None else row["MC J mean"], row[tables.PREDICTED])
             for row in rows]
    return [w for w in lines if w]


def echo_warnings(lines) -> list[str]:
    """Each warning as one line on stderr; returns them (for the report)."""
    for line in lines:
        click.echo(line, err=True)
    return list(lines)


def warnings_section(lines) -> str:
    """The markdown section of a report that lists the warnings ('' without any)."""
    return "" if not lines else "\n## Warnings\n\n" + "\n".join(f"- {w}" for w in lines) + "\n"


def _perturb_outputs(results, staging: pathlib.Path, settings: dict, table_rows, warned=()) -> None:
    from ..plot import perturbation_figures
    records = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
               for row in table_rows]
    report.write_json(staging / "perturb.json", dict(settings=settings, results=records))
    write_text(staging / "perturb.md", tables.markdown_table(tables.records_table(table_rows)) + "\n"
               + warnings_section(warned))
    arrays = {}
    for r in results:
        tag = f"ls{int(round(1000 * r.sensory_delay))}ms"
        arrays[f"{tag}_x_mean"] = np.asarray(r.base.x).mean(axis=0)
        arrays[f"{tag}_x_kicked_mean"] = np.asarray(r.perturbed.x).mean(axis=0)
        arrays[f"{tag}_u_mean"] = np.asarray(r.base.u).mean(axis=0)
        arrays[f"{tag}_u_kicked_mean"] = np.asarray(r.perturbed.u).mean(axis=0)
        arrays[f"{tag}_disturbance"] = r.disturbance
    savez(staging / "perturb_means.npz", arrays, compressed=True)
    report.save_figures(perturbation_figures(results), staging)


@click.command("perturb")
@click.argument("model", type=click.Choice(perturbation.PERTURB_MODELS), metavar="MODEL")
@click.option("--delay", type=float, default=0.05, show_default=True,
              help="Input (motor) delay in seconds (a whole number of the model's time steps).")
@click.option("--sensory-delays", type=DelayList(), default="0,0.05,0.1", show_default=True,
              help="Comma-separated sensory delays in seconds, each a whole number of the model's time steps.")
@click.option("--pulse-time", type=click.FloatRange(min=0.0), default=0.15, show_default=True,
              help="When the kick hits, in seconds from the start of the movement.")
@click.option("--kick", type=click.FloatRange(min=0.0, min_open=True), default=0.2, show_default=True,
              help="Size of the kick: the change of the hand's (point's) velocity in m/s, perpendicular "
                   "to the nominal movement.")
@click.option("--trials", type=click.IntRange(min=1), default=200, show_default=True,
              help="Monte Carlo trials per sensory delay (each run twice: without and with the kick).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the motor and sensory noise.")
@noise_option
@progress_option
@out_option(default=None, help="Folder for perturb.json, perturb.md, perturb_means.npz and perturbation.png.")
def perturb_command(model, delay, sensory_delays, pulse_time, kick, trials, seed, noise, no_noise, progress, out,
                    overwrite):
    """Perturbation experiments: kick the hand of MODEL mid-reach and measure the correction
    against the sensory delay.

    MODEL is point_mass, arm2 or arm2_muscle6, with their default sensors (docs/models.md); the
    motor noise is --noise (the sensors are always noisy). Per sensory delay the controller and the
    delayed filter are designed, and --trials trials run without and with the kick on the same
    noise; the first command that differs is (1 + l_s) steps after the kick.
    """
    noise = noise_value(noise, no_noise)
    try:
        problems = [REGISTRY[model].factory(delay=delay, noise=noise, sensory_delay=ls) for ls in sensory_delays]
    except ValueError as exc:
        hint = "'--noise'" if str(exc).startswith("noise") else "'--delay' / '--sensory-delays'"
        raise click.BadParameter(str(exc), param_hint=hint) from exc
    final = problems[0].horizon * problems[0].dt
    if pulse_time >= final:
        raise click.BadParameter(f"must be within the movement, below {final:g} s; got {pulse_time:g}",
                                 param_hint="'--pulse-time'")
    check_trials(problems[-1], trials, 1, runs=2 * len(sensory_delays))
    with Output(out, overwrite) as output:
        results = perturbation.perturbation_study(model, sensory_delays, delay, pulse_time, kick, trials, seed,
                                                  noise=noise, progress=progress)
        rows = _perturb_rows(results)
        click.echo(tables.text_table(tables.records_table(rows)))
        warned = echo_warnings(_perturb_warnings(rows))
        if out is not None:
            settings = dict(model=model, delay=delay, sensory_delays=list(sensory_delays), pulse_time=pulse_time,
                            kick=kick, trials=trials, seed=seed, noise=noise is not False,
                            problems=[problem_record(p) for p in problems])
            _perturb_outputs(results, output.staging, settings, rows, warned)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    failed = [r for r in results if not r.converged]
    for r in failed:
        click.echo(f"warning: the solve at sensory delay {r.sensory_delay:g} s did not converge "
                   f"({r.solution.status})", err=True)
    if failed:
        sys.exit(1)
