"""The ``fit`` command: cost weights and noise scales fitted to reach data, the delay by a profile."""
from __future__ import annotations

import math
import pathlib
import sys
import time

import click

from ..experiments import report, tables
from ..experiments.records import problem_record
from .arguments import DelayList, ParamPair, import_callable, progress_option
from .output import Output, out_option


@click.command("fit")
@click.argument("function", metavar="FUNCTION")
@click.argument("data", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option("--start", "starts", type=ParamPair(), multiple=True, required=True,
              help="name=value: a fitted parameter and its starting value (a positive number); repeatable.")
@click.option("--delays", type=DelayList(), required=True,
              help="Comma-separated candidate delays in seconds (the profile: one fit per delay).")
@click.option("--mean-scale", type=click.FloatRange(min=0.0, min_open=True), default=1e-3, show_default=True,
              help="Precision of a mean path in task units (e.g. its standard error).")
@click.option("--max-iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="L-BFGS-B iterations per delay.")
@click.option("--gtol", type=click.FloatRange(min=0.0, min_open=True), default=1e-8, show_default=True,
              help="L-BFGS-B's tolerance on the projected gradient of the loss in log parameters.")
@progress_option
@out_option(default=None, help="Folder for fit.json.")
def fit_command(function, data, starts, delays, mean_scale, max_iterations, gtol, progress, out, overwrite):
    """Fit cost weights and noise scales to reach data, and the delay by a profile (docs/fitting.md).

    FUNCTION is package.module:name, called as name(params, condition, delay) with params a dict
    of the --start names (traced scalars), condition one row of DATA's conditions and delay in
    seconds, and returning a delayed_ilqr.Problem. DATA is an NPZ file with the arrays conditions
    [C, ...], mean [C, K+1, m] (mean task-space paths) and endpoint_cov [C, m, m]
    (delayed_ilqr.experiments.fitting.save_reach_data writes one). Prints the loss and parameters
    fitted at each delay and the delay of the smallest loss; exits 1 when that fit did not
    converge (results are still written).
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
    for delay in delays:
        try:
            problem = make_problem({k: float(v) for k, v in params0.items()}, conditions[0], delay)
        except ValueError as exc:
            raise click.BadParameter(f"{function} refused delay {delay:g} s: {exc}", param_hint="'--delays'") from None
        try:
            fitting.check_reach_data(problem, len(conditions), reach_data)
        except ValueError as exc:
            raise click.BadParameter(f"{data} does not fit {function} at delay {delay:g} s: {exc}",
                                     param_hint="'DATA'") from None
    with Output(out, overwrite) as output:
        start = time.perf_counter()
        best, fits = fitting.profile_delay(make_problem, delays, conditions, reach_data,
                                           {k: float(v) for k, v in params0.items()}, mean_scale=mean_scale,
                                           max_iterations=max_iterations, gtol=gtol, progress=progress)
        elapsed = time.perf_counter() - start
        names = sorted(params0)
        header = ["delay [s]", "loss", *names, "converged", "L-BFGS-B iterations", "evaluations"]
        rows = [[f"{d:g}", f"{f.loss:.4g}", *(f"{f.params[k]:.6g}" for k in names), "yes" if f.converged else "no",
                 str(f.iterations), str(f.evaluations)] for d, f in zip(delays, fits)]
        click.echo(tables.text_table((header, rows)))
        chosen = fits[delays.index(best)]
        click.echo(f"delay {best:g} s (smallest loss); " + ", ".join(f"{k} = {chosen.params[k]:.6g}" for k in names))
        if out is not None:
            # the problem of the first condition at the first delay and the starting values, and
            # the one fitted (the chosen delay and parameters)
            settings = dict(function=function, data=str(data), start=params0, delays=list(delays),
                            mean_scale=mean_scale, max_iterations=max_iterations, gtol=gtol,
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
        click.echo(f"warning: the fit at delay {best:g} s did not converge: {chosen.message}", err=True)
        sys.exit(1)
