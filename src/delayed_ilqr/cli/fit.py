"""The ``fit`` command: cost weights and noise scales fitted to reach data, the delay by a profile
over whole steps or, with ``--fit-delay``, by gradient with the others."""
from __future__ import annotations

import math
import pathlib
import sys
import time

import click

from ..experiments import report, tables
from ..experiments.delay_text import delay_text
from ..experiments.records import problem_record
from .arguments import DelayList, ParamPair, import_callable, progress_option
from .output import Output, out_option


@click.command("fit")
@click.argument("function", metavar="FUNCTION")
@click.argument("data", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option("--start", "starts", type=ParamPair(), multiple=True,
              help="name=value: a fitted parameter and its starting value (a positive number); repeatable "
                   "(at least one, unless --fit-delay fits the delay alone).")
@click.option("--delays", type=DelayList(), required=True,
              help="Comma-separated candidate delays in seconds (the profile: one fit per delay).")
@click.option("--mean-scale", type=click.FloatRange(min=0.0, min_open=True), default=1e-3, show_default=True,
              help="Precision of a mean path in task units (e.g. its standard error).")
@click.option("--max-iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="L-BFGS-B iterations per delay.")
@click.option("--gtol", type=click.FloatRange(min=0.0, min_open=True), default=1e-8, show_default=True,
              help="L-BFGS-B's tolerance on the projected gradient of the loss in log parameters.")
@click.option("--ftol", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="L-BFGS-B's tolerance on the relative decrease of the loss in one iteration (0: none).")
@click.option("--fit-delay", is_flag=True,
              help="Fit the motor delay by gradient with the other parameters (a fractional delay, "
                   "docs/derivation.md §20), from the one delay given by --delays, instead of a profile.")
@click.option("--per-channel", is_flag=True, help="With --fit-delay: one delay per command channel.")
@click.option("--max-delay", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="With --fit-delay: the longest delay the fit may reach, in seconds (default twice the start).")
@progress_option
@out_option(default=None, help="Folder for fit.json.")
def fit_command(function, data, starts, delays, mean_scale, max_iterations, gtol, ftol, fit_delay, per_channel, max_delay,
                progress, out, overwrite):
    """Fit cost weights and noise scales to reach data, and the delay by a profile (docs/fitting.md).

    FUNCTION is package.module:name, called as name(params, condition, delay) with params a dict
    of the --start names (traced scalars), condition one row of DATA's conditions and delay in
    seconds, and returning a delayed_ilqr.Problem. DATA is an NPZ file with the arrays conditions
    [C, ...], mean [C, K+1, m] (mean task-space paths) and endpoint_cov [C, m, m]
    (delayed_ilqr.experiments.fitting.save_reach_data writes one). Prints the loss and parameters
    fitted at each delay and the delay of the smallest loss; exits 1 when that fit did not
    converge (results are still written). The profile's delays must be whole steps of the
    model's dt. With --fit-delay the delay (one, or one per channel with --per-channel) is a
    fitted parameter ("delay", or "delay_0", ...), started at the one value of --delays; FUNCTION
    is then called at that delay and may depend on it only through the problem's delay_steps.
    """
    from ..experiments import fitting

    try:
        make_problem = import_callable(function, "FUNCTION", None, None)
    except click.BadParameter as exc:
        exc.param_hint = "'FUNCTION'"
        raise
    try:
        conditions, reach_data = fitting.load_reach_data(data)
    except (ValueError, OSError) as exc:
        raise click.BadParameter(str(exc), param_hint="'DATA'") from None
    params0 = dict(starts)
    bad = {k: v for k, v in params0.items()
           if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0)}
    if bad:
        raise click.BadParameter(f"starting values must be positive finite numbers; got {bad}", param_hint="'--start'")
    if not params0 and not fit_delay:
        raise click.BadParameter("give at least one parameter to fit, name=value", param_hint="'--start'")
    if fit_delay and len(delays) != 1:
        raise click.BadParameter(f"with --fit-delay, give one starting delay; got {len(delays)}: {list(delays)}",
                                 param_hint="'--delays'")
    if (per_channel or max_delay is not None) and not fit_delay:
        raise click.BadParameter("--per-channel and --max-delay need --fit-delay", param_hint="'--fit-delay'")
    if fit_delay and (delays[0] <= 0 or (max_delay is not None and max_delay < delays[0])):
        raise click.BadParameter(f"the starting delay must be positive and at most --max-delay; got {delays[0]!r} "
                                 f"(--max-delay {max_delay!r})", param_hint="'--delays'")
    for delay in delays:
        try:
            problem = make_problem({k: float(v) for k, v in params0.items()}, conditions[0], delay)
        except ValueError as exc:
            raise click.BadParameter(f"{function} refused delay {delay:g} s: {exc}", param_hint="'--delays'") from None
        if problem.is_fractional and not fit_delay:
            raise click.BadParameter(f"a profile's delays must be whole steps of dt={problem.dt!r} s; got {delay!r} s "
                                     f"({delay / problem.dt:.10g} steps): use --fit-delay to fit a delay between "
                                     "steps", param_hint="'--delays'")
        try:
            fitting.check_reach_data(problem, len(conditions), reach_data)
        except ValueError as exc:
            raise click.BadParameter(f"{data} does not fit {function} at delay {delay:g} s: {exc}",
                                     param_hint="'DATA'") from None
    if fit_delay:
        _fit_delay(function, make_problem, data, conditions, reach_data, params0, delays[0],
                   2 * delays[0] if max_delay is None else max_delay, per_channel, mean_scale, max_iterations, gtol,
                   ftol, progress, out, overwrite)
        return
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        best, fits = fitting.profile_delay(make_problem, delays, conditions, reach_data,
                                           {k: float(v) for k, v in params0.items()}, mean_scale=mean_scale,
                                           max_iterations=max_iterations, gtol=gtol, ftol=ftol,
                                           progress=progress)
        elapsed = time.perf_counter() - start
        names = sorted(params0)
        header = ["delay [s]", "loss", *names, "converged", "L-BFGS-B iterations", "evaluations"]
        rows = [[f"{d:g}", f"{f.loss:.4g}", *(f"{f.params[k]:.6g}" for k in names), "yes" if f.converged else "no",
                 str(f.iterations), str(f.evaluations)] for d, f in zip(delays, fits)]
        click.echo(tables.text_table((header, rows)))
        chosen = fits[delays.index(best)]
        click.echo(f"delay {delay_text(best)} (smallest loss); "
                   + ", ".join(f"{k} = {chosen.params[k]:.6g}" for k in names))
        if out is not None:
            # the problem of the first condition at the first delay and the starting values, and
            # the one fitted (the chosen delay and parameters)
            settings = dict(function=function, data=str(data), start=params0, delays=list(delays),
                            mean_scale=mean_scale, max_iterations=max_iterations, gtol=gtol, ftol=ftol,
                            elapsed_seconds=elapsed,
                            problem=problem_record(make_problem({k: float(v) for k, v in params0.items()},
                                                                conditions[0], delays[0])),
                            fitted_problem=problem_record(make_problem(chosen.params, conditions[0], best)))
            records = [dict(delay=d, loss=f.loss, params=f.params, converged=f.converged, message=f.message,
                            iterations=f.iterations, evaluations=f.evaluations) for d, f in zip(delays, fits)]
            report.write_json(output.staging / "fit.json", dict(settings=settings, best_delay=best, fits=records))
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if not chosen.converged:
        click.echo(f"warning: the fit at delay {delay_text(best)} did not converge: {chosen.message}", err=True)
        sys.exit(1)


def _fit_delay(function, make_problem, data, conditions, reach_data, params0, delay0, max_delay, per_channel,
               mean_scale, max_iterations, gtol, ftol, progress, out, overwrite):
    """``fit --fit-delay``: one fit of the delays with the other parameters (experiments/delay_fitting)."""
    from ..experiments import delay_fitting
    from ..experiments.progress import progress_bar

    start = time.perf_counter()
    with progress_bar(max_iterations, "fit", "evaluation", progress) as bar:
        shown = lambda n, loss: bar.set_postfix_str(f"evaluation {n}, loss {loss:.4g}")  # noqa: E731
        try:
            result, model = delay_fitting.fit_delays(
                make_problem, conditions, reach_data, {k: float(v) for k, v in params0.items()}, delay0, max_delay,
                per_channel=per_channel, mean_scale=mean_scale, max_iterations=max_iterations, gtol=gtol,
                ftol=ftol, on_evaluation=shown)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--max-delay'") from None
    elapsed = time.perf_counter() - start
    names = sorted(result.params)
    header = ["loss", *names, "converged", "L-BFGS-B iterations", "evaluations"]
    row = [f"{result.loss:.4g}", *(f"{result.params[k]:.6g}" for k in names), "yes" if result.converged else "no",
           str(result.iterations), str(result.evaluations)]
    click.echo(tables.text_table((header, [row])))
    if out is not None:
        with Output(out, overwrite) as output:
            fitted = model(result.params, conditions[0])
            settings = dict(function=function, data=str(data), start=params0, delay0=delay0, max_delay=max_delay,
                            per_channel=per_channel, mean_scale=mean_scale, max_iterations=max_iterations, gtol=gtol,
                            ftol=ftol, elapsed_seconds=elapsed, frame=model.frame,
                            problem=problem_record(make_problem({k: float(v) for k, v in params0.items()},
                                                                conditions[0], delay0)),
                            fitted_delay_steps=[float(v) for v in (fitted.delay_in_steps if fitted.is_fractional
                                                                   else [fitted.delay_steps])])
            record = dict(loss=result.loss, params=result.params, converged=result.converged, message=result.message,
                          iterations=result.iterations, evaluations=result.evaluations)
            report.write_json(output.staging / "fit.json", dict(settings=settings, fit=record))
            written = output.commit(settings)
        click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if not result.converged:
        click.echo(f"warning: the fit did not converge: {result.message}", err=True)
        sys.exit(1)
