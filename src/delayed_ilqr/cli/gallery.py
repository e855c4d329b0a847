"""The gallery's commands: ``kick``, ``target-jump``, ``fitts`` and ``minimal-intervention``, each a
classic experiment of human motor control run on an arm (`delayed_ilqr.experiments`), printed
as a table of published against measured numbers and, with ``--out``, written atomically as
``<name>.json`` (settings, every number), ``<name>.md`` (the table, warnings, the figure) and
``<name>.png`` with its ``manifest.json``."""
from __future__ import annotations

import math
import time

import click
import numpy as np

from .._files import write_text
from ..experiments import (delay_growth, fitts, kick, minimal_intervention, reach_tasks, report, tables,
                           target_jump)
from ..experiments.delay_text import delay_text
from ..experiments.records import problem_record
from ..statistics import divergence_bound, diverged_trials, prediction_warning, sample_stats
from .arguments import SEED, DelayList
from .output import Output, out_option

ARM = click.option("--arm", type=click.Choice(reach_tasks.ARMS), default="arm2_muscle6", show_default=True,
                   help="arm2_muscle6 (six muscles, its defaults) or arm2 (torque-driven, its human preset; faster).")


class ModelDelay(click.ParamType):
    """A delay in seconds, ``model`` (the model's default) or, where ``none`` is allowed, ``none``
    (no sensors: the state is seen)."""

    name = "SECONDS|model"

    def __init__(self, allow_none: bool = False):
        self.allow_none = allow_none
        if allow_none:
            self.name = "SECONDS|model|none"

    def convert(self, value, param, ctx):
        if value is None or (isinstance(value, str) and value.strip().lower() == "none" and self.allow_none):
            return None
        if isinstance(value, str) and value.strip().lower() == reach_tasks.MODEL_DEFAULT:
            return reach_tasks.MODEL_DEFAULT
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            self.fail(f"must be a delay in seconds or 'model'{' or none' if self.allow_none else ''}; got {value!r}",
                      param, ctx)
        if not math.isfinite(seconds) or seconds < 0:
            self.fail(f"must be a non-negative number of seconds; got {value!r}", param, ctx)
        return seconds


DELAY = click.option("--delay", type=ModelDelay(), default=reach_tasks.MODEL_DEFAULT, show_default=True,
                     help="Motor delay (s), or 'model': the model's default.")
SENSORY_DELAY = click.option("--sensory-delay", type=ModelDelay(allow_none=True), default=reach_tasks.MODEL_DEFAULT,
                             show_default=True, help="Sensory delay (s), 'model' (the model's default sensors) or "
                                                     "'none' (the state is seen).")
TRIALS = click.option("--trials", type=click.IntRange(min=2), default=200, show_default=True,
                      help="Monte Carlo trials (each condition runs on the same noise).")
SEED_OPTION = click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the noise.")
DISTURBANCE_MODEL = click.option("--disturbance-model", type=click.FloatRange(min=0.0, min_open=True), default=None,
                                 help="The filter expects external joint torques of this density (N m s^1/2, "
                                      "e.g. 0.05); the plant is unchanged.  [default: none]")

CONTROLLER = click.option("--controller", type=click.Choice(["replanning", "fixed"]), default="replanning",
                          show_default=True,
                          help="The model's controller, which re-plans from its filter's estimate at every tick "
                               "(replanning), or the fixed feedback law of one solve (fixed).")


def _check(arm, **kwargs):
    """Builds the reach once, so that a delay off the grid is a usage error naming the option."""
    try:
        reach_tasks.reach(arm, **kwargs)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--delay' / '--sensory-delay'") from None


def _finish(name: str, title: str, rows: list, warned: list, records: dict, figure, out, overwrite_output,
            settings: dict, elapsed: float, statuses=()):
    """Prints the table and the warnings (and one line per solve that did not converge); with --out
    writes the files and commits the folder."""
    from .. import Status
    warned = list(warned) + [f"warning: a solve of the {name} experiment did not converge ({s}); its numbers are "
                             "those of the returned policy" for s in dict.fromkeys(map(str, statuses))
                             if not Status[s].converged]
    table = tables.records_table(rows)
    click.echo(tables.text_table(table))
    for line in warned:
        click.echo(line, err=True)
    if out is None:
        return
    staging = overwrite_output.staging
    settings = dict(settings, elapsed_seconds=elapsed)
    report.write_json(staging / f"{name}.json", report.json_ready(dict(settings=settings, warnings=warned,
                                                            descriptions=report.DESCRIPTIONS, **records)))
    report.save_figures({f"{name}.png": figure}, staging)
    md = [f"# {title}", "", tables.markdown_table(table), ""]
    if warned:
        md += ["## Warnings", ""] + [f"- {w}" for w in warned] + [""]
    md += [f"![{name}]({name}.png)", "", f"Run time {elapsed:.1f} s.", ""]
    write_text(staging / f"{name}.md", "\n".join(md))
    written = overwrite_output.commit(settings)
    click.echo(f"wrote {', '.join(written)} to {out}")


def _cost_warnings(label, cost, predicted, problem) -> list:
    """The Monte Carlo mean cost (trials that did not diverge, one definition) against the local
    (linearised) prediction: [one line] when they differ by more than 2x, else []."""
    cost = np.asarray(cost)
    mean = sample_stats(cost, diverged_trials(cost, divergence_bound(problem))).mean
    line = prediction_warning(label, mean, float(predicted))
    return [line] if line else []


@click.command("kick")
@ARM
@DELAY
@SENSORY_DELAY
@click.option("--kick", "size", type=click.FloatRange(min=0.0, min_open=True), default=0.15, show_default=True,
              help="Change of the hand's speed (m/s), perpendicular to the movement.")
@click.option("--pulse-time", type=click.FloatRange(min=0.0), default=None,
              help="When the kick hits (s from the start).  [default: mid-movement]")
@TRIALS
@SEED_OPTION
@DISTURBANCE_MODEL
@CONTROLLER
@click.option("--innovation-gate", "gate", type=click.FloatRange(min=0.0, max=1.0, min_open=True, max_open=True),
              default=None, help="The re-planning controller's filter believes a push when a measurement is this "
                                 "improbable (false-alarm probability per sample, e.g. 0.05).  [default: none]")
@out_option(default=None, help="Folder for the JSON record, the Markdown report and the figure (kick.*).")
def kick_command(arm, delay, sensory_delay, size, pulse_time, trials, seed, disturbance_model, controller, gate, out,
                 overwrite):
    """A mid-reach kick of the hand: latency of the first command change and final error.

    The same trials run without and with the kick on the same noise; the first change of the
    applied command can come no earlier than the loop latency (sensory + motor delay).
    """
    _check(arm, delay=delay, sensory_delay=sensory_delay)
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        r = kick.kick_experiment(arm, delay, sensory_delay, size, pulse_time, trials, seed,
                                 disturbance_model=disturbance_model, controller=controller, gate=gate)
        elapsed = time.perf_counter() - start
        warned = _cost_warnings("kick, unperturbed trials", r.base.runs.cost, r.solution.expected_cost, r.problem)
        a = r.analysis
        records = dict(comparison=kick.comparison(r), status=str(r.solution.status),
                       analysis=dict(first_change=a.first_change, onset=a.onset, loop_latency=a.loop_latency,
                                     peak_displacement=a.peak_displacement, error_base=a.error_base,
                                     error_kicked=a.error_kicked, error_ratio=a.error_ratio, believed=a.believed),
                       predicted_cost=float(r.solution.expected_cost), controller=controller,
                       solver_failures=r.solver_failures, unperturbed=_profiles(r))
        from ..plot.gallery import plot_kick
        settings = dict(arm=arm, delay=delay, sensory_delay=sensory_delay, kick=size, pulse_time=pulse_time,
                        trials=trials, seed=seed, disturbance_model=disturbance_model, controller=controller,
                        innovation_gate=gate, problem=problem_record(r.problem))
        _finish("kick", "A mid-reach kick", kick.comparison(r), warned, records, plot_kick(r), out, output, settings,
                elapsed, [r.solution.status])


def _profiles(r) -> dict:
    """The unperturbed reach of each controller the kick ran (`replanning.reach_profile`)."""
    from ..experiments.replanning import reach_profile
    out = {r.controller: reach_profile(r.base, r.problem.dt)._asdict()}
    if r.fixed_base is not None:
        out["fixed"] = reach_profile(r.fixed_base, r.problem.dt)._asdict()
    return out


@click.command("target-jump")
@ARM
@DELAY
@SENSORY_DELAY
@click.option("--jump", type=click.FloatRange(min=0.0, min_open=True), default=0.02, show_default=True,
              help="Target displacement (m), perpendicular to the movement.")
@click.option("--times", type=DelayList(), default="0.1,0.2,0.3,0.4", show_default=True,
              help="Comma-separated jump times, seconds before the end of the movement.")
@click.option("--final-time", type=click.FloatRange(min=0.0, min_open=True), default=0.6, show_default=True,
              help="Movement time (s).")
@TRIALS
@SEED_OPTION
@DISTURBANCE_MODEL
@CONTROLLER
@out_option(default=None, help="Folder for the JSON record, the Markdown report and the figure (target_jump.*).")
def target_jump_command(arm, delay, sensory_delay, jump, times, final_time, trials, seed, disturbance_model,
                        controller, out, overwrite):
    """Target jumps (Liu & Todorov 2007) at several times before the end of the reach.

    The target is seen through the arm's sensors (same delay), so the correction can start one
    loop latency (sensory + motor delay) after the jump.
    """
    _check(arm, delay=delay, sensory_delay=sensory_delay, final_time=final_time)
    if any(not 0 < t < final_time for t in times):
        raise click.BadParameter(f"each time must lie in (0, {final_time:g}) s; got {times}", param_hint="'--times'")
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        r = target_jump.target_jump_experiment(arm, delay, sensory_delay, jump, times, trials, seed,
                                               final_time=final_time, disturbance_model=disturbance_model,
                                               controller=controller)
        elapsed = time.perf_counter() - start
        records = dict(comparison=target_jump.comparison(r), status=str(r.solution.status),
                       analyses=[a._asdict() for a in r.analyses], predicted_cost=float(r.solution.expected_cost),
                       controller=controller, solver_failures=r.solver_failures)
        from ..plot.gallery import plot_target_jump
        settings = dict(arm=arm, delay=delay, sensory_delay=sensory_delay, jump=jump, times=list(times),
                        final_time=final_time, trials=trials, seed=seed, disturbance_model=disturbance_model,
                        controller=controller, problem=problem_record(r.problem))
        warned = _cost_warnings("target jump, trials without a jump", r.base_cost, r.solution.expected_cost, r.problem)
        _finish("target_jump", "Target jumps", target_jump.comparison(r), warned, records, plot_target_jump(r), out,
                output, settings, elapsed, [r.solution.status])


@click.command("fitts")
@ARM
@click.option("--delays", type=DelayList(), default=None,
              help="Comma-separated motor delays (s); one fit per delay.  [default: the model's, and 0.12]")
@SENSORY_DELAY
@click.option("--distances", type=DelayList(), default=",".join(f"{d:g}" for d in fitts.DISTANCES), show_default=True,
              help="Comma-separated movement distances (m).")
@click.option("--widths", type=DelayList(), default=",".join(f"{w:g}" for w in fitts.WIDTHS), show_default=True,
              help="Comma-separated target widths (m); Fitts 1954's are 0.00635,0.0127,0.0254,0.0508.")
@click.option("--movement-times", type=DelayList(), show_default=True,
              default=",".join(f"{t:g}" for t in fitts.MOVEMENT_TIMES),
              help="Comma-separated movement times (s, increasing): the grid the model chooses from.")
@click.option("--trials", type=click.IntRange(min=2), default=100, show_default=True,
              help="Monte Carlo trials per distance and movement time.")
@SEED_OPTION
@out_option(default=None, help="Folder for the JSON record, the Markdown report and the figure (fitts.*).")
def fitts_command(arm, delays, sensory_delay, distances, widths, movement_times, trials, seed, out, overwrite):
    """Fitts' law: the shortest movement time that meets the accuracy criterion, against log2(2D/W).

    All distances and movement times at one delay are solved in one vmapped call.
    """
    delays = [reach_tasks.MODEL_DEFAULT, 0.12] if delays is None else delays
    for d in delays:
        _check(arm, delay=d, sensory_delay=sensory_delay)
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        try:
            results = fitts.fitts_experiment(arm, distances, widths, movement_times, delays, sensory_delay,
                                             trials=trials, seed=seed)
        except ValueError as exc:
            raise click.UsageError(str(exc)) from None
        elapsed = time.perf_counter() - start
        records = dict(comparison=fitts.comparison(results),
                       results=[dict(delay=r.delay, distances=r.distances, widths=r.widths,
                                     sensory_delay=r.sensory_delay, movement_times=r.movement_times, bias=r.bias,
                                     sd=r.sd, problem=problem_record(r.problem), mc_cost=r.mc_cost,
                                     predicted_cost=r.predicted_cost,
                                     status=r.status.tolist(), mt=r.mt, index=r.index,
                                     fit=None if r.fit is None else r.fit._asdict()) for r in results])
        from ..plot.gallery import plot_fitts
        settings = dict(arm=arm, delays=list(delays), sensory_delay=sensory_delay, distances=list(distances),
                        widths=list(widths), movement_times=list(movement_times), trials=trials, seed=seed)
        warned = []
        for r in results:
            bad = [prediction_warning("", m, q) for m, q in zip(r.mc_cost.ravel(), r.predicted_cost.ravel())]
            if any(bad):
                worst = int(np.nanargmax(np.abs(np.log(r.mc_cost.ravel() / r.predicted_cost.ravel()))))
                warned.append(prediction_warning(
                    f"fitts at motor delay {delay_text(r.delay)}, {sum(map(bool, bad))} of {len(bad)} conditions "
                    "(the worst shown)", r.mc_cost.ravel()[worst], r.predicted_cost.ravel()[worst]))
        _finish("fitts", "Fitts' law", fitts.comparison(results), warned, records, plot_fitts(results), out, output,
                settings, elapsed, [s for r in results for s in r.status.ravel()])


@click.command("minimal-intervention")
@ARM
@DELAY
@SENSORY_DELAY
@TRIALS
@SEED_OPTION
@out_option(default=None, help="Folder for minimal_intervention.json, .md, .png.")
def minimal_intervention_command(arm, delay, sensory_delay, trials, seed, out, overwrite):
    """Minimal intervention: endpoint scatter of a bar target against a point target."""
    _check(arm, delay=delay, sensory_delay=sensory_delay)
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        scatters = minimal_intervention.minimal_intervention_experiment(arm, delay, sensory_delay, trials, seed)
        elapsed = time.perf_counter() - start
        records = dict(comparison=minimal_intervention.comparison(scatters),
                       targets=[dict(name=s.name, irrelevant_sd=s.irrelevant, relevant_sd=s.relevant, ratio=s.ratio,
                                     ellipse=s.ellipse._asdict(), status=s.status) for s in scatters])
        from ..plot.gallery import plot_minimal_intervention
        settings = dict(arm=arm, delay=delay, sensory_delay=sensory_delay, trials=trials, seed=seed,
                        problems={s.name: problem_record(s.problem) for s in scatters})
        warned = [w for sc in scatters
                  for w in _cost_warnings(f"{sc.name} target", sc.mc_cost, sc.predicted_cost, sc.problem)]
        _finish("minimal_intervention", "Minimal intervention", minimal_intervention.comparison(scatters), warned,
                records, plot_minimal_intervention(scatters), out, output, settings, elapsed,
                [s.status for s in scatters])


@click.command("delay-growth")
@ARM
@click.option("--delays", type=DelayList(), default=",".join(f"{d:g}" for d in delay_growth.MOTOR_DELAYS),
              show_default=True, help="Comma-separated motor delays (s), at the model's sensory delay.")
@click.option("--sensory-delays", type=DelayList(), show_default=True,
              default=",".join(f"{d:g}" for d in delay_growth.SENSORY_DELAYS),
              help="Comma-separated sensory delays (s), at the model's motor delay.")
@click.option("--targets", type=click.IntRange(min=1), default=4, show_default=True,
              help="Hand targets on the 10 cm circle, pooled (one batched solve per delay).")
@click.option("--trials", type=click.IntRange(min=2), default=100, show_default=True,
              help="Monte Carlo trials per target and delay (the same noise at every delay).")
@SEED_OPTION
@out_option(default=None, help="Folder for delay_growth.json, .md, .png.")
def delay_growth_command(arm, delays, sensory_delays, targets, trials, seed, out, overwrite):
    """Cost, endpoint error and scatter against the motor and the sensory delay.

    Monte Carlo (common noise across delays) beside the local (linearised) prediction; each
    quantity should grow monotonically with each delay.
    """
    for d in delays:
        _check(arm, delay=d)
    for d in sensory_delays:
        _check(arm, sensory_delay=d)
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        r = delay_growth.delay_growth_experiment(arm, delays, sensory_delays, targets, trials, seed)
        elapsed = time.perf_counter() - start
        rows = delay_growth.comparison(r)
        records = dict(comparison=rows, motor=[p._asdict() for p in r.motor], sensory=[p._asdict() for p in r.sensory])
        from ..plot.gallery import plot_delay_growth
        settings = dict(arm=arm, delays=list(delays), sensory_delays=list(sensory_delays), targets=targets,
                        trials=trials, seed=seed, problem=problem_record(r.problem))
        def label(p):
            sensory = "none" if p.sensory_delay is None else f"{1e3 * p.sensory_delay:.0f} ms"
            return f"delay growth at motor {delay_text(p.delay)}, sensory {sensory}"
        warned = [w for w in (prediction_warning(label(p), p.cost.mean, p.predicted_cost)
                              for p in r.motor + r.sensory) if w]
        _finish("delay_growth", "Cost, error and scatter against the delay", rows, warned, records,
                plot_delay_growth(r), out, output, settings, elapsed,
                [s for p in r.motor + r.sensory for s in p.statuses])


COMMANDS = (kick_command, target_jump_command, fitts_command, minimal_intervention_command, delay_growth_command)

