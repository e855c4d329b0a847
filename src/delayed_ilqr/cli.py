"""The ``delayed-ilqr`` command line: glue between the library, files and figures (no numerics here).

Subcommands: ``models``, ``solve``, ``simulate``, ``compare`` and ``demo`` (``delayed-ilqr --help``).
Exit codes: 0 success; 1 when some solve did not converge (results are still written); 2 for bad
arguments (unknown model, a delay that is not a whole number of steps, a non-positive trial count).
"""
from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import sys
import time
from typing import Optional, Sequence

import click
import numpy as np

from . import center_out, study
from .models import REGISTRY, arm2_muscle6
from .options import Options
from .solution import Status

__all__ = ["main"]

DEMO_DELAYS = (0.0, 0.05, 0.1)
_MODEL = click.Choice(sorted(REGISTRY))
_OUT_TYPE = click.Path(file_okay=False, dir_okay=True, writable=True, path_type=pathlib.Path)
_DPI = 120


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------

class _DelayList(click.ParamType):
    """A comma-separated list of non-negative delays in seconds, e.g. ``0,0.05,0.1``."""

    name = "SECONDS[,SECONDS...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (list, tuple)):
            return list(value)
        try:
            delays = [float(v) for v in str(value).split(",") if v.strip()]
        except ValueError:
            self.fail(f"must be comma-separated numbers of seconds such as 0,0.05,0.1; got {value!r}", param, ctx)
        if not delays:
            self.fail(f"must name at least one delay; got {value!r}", param, ctx)
        bad = [d for d in delays if not math.isfinite(d) or d < 0]
        if bad:
            self.fail(f"delays must be non-negative finite numbers of seconds; got {bad[0]!r}", param, ctx)
        return delays


def _problem(model: str, delay: float, noise: bool, hint: str = "--delay"):
    """The model's problem; the factory's refusal of a delay becomes a usage error (exit code 2)."""
    try:
        return REGISTRY[model].factory(delay=delay, noise=noise)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint=f"'{hint}'") from exc


def _out_dir(out: Optional[pathlib.Path]) -> Optional[pathlib.Path]:
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    return out


def _write_json(path: pathlib.Path, data) -> None:
    path.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")


def _json_float(value) -> Optional[float]:
    value = float(value)
    return value if math.isfinite(value) else None


def _save_figure(fig, path: pathlib.Path) -> None:
    fig.savefig(path, dpi=_DPI)


def _policy_arrays(sol) -> dict:
    p, t = sol.policy, sol.trace
    n = int(sol.iterations) + 1
    return dict(x_nominal=np.asarray(p.x_nominal), u_nominal=np.asarray(p.u_nominal),
                feedforward=np.asarray(p.feedforward), state_feedback=np.asarray(p.state_feedback),
                delay_feedback=np.asarray(p.delay_feedback), trace_cost=np.asarray(t.cost[:n]),
                trace_merit=np.asarray(t.merit[:n]), trace_step_size=np.asarray(t.step_size[:n]),
                trace_reg=np.asarray(t.reg[:n]), trace_grad_norm=np.asarray(t.grad_norm[:n]))


def _table(rows: Sequence[tuple[str, str]]) -> str:
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def _fmt(value: float) -> str:
    return study._num(float(value))


def _endpoint_text(result: study.ControllerResult) -> str:
    scale, unit = study._unit_scale(result.endpoint_unit)
    e = result.endpoint_error
    if math.isfinite(e.mean):
        return f"{_fmt(scale * e.mean)} {unit} (95% CI {_fmt(scale * e.ci95[0])} to {_fmt(scale * e.ci95[1])})"
    return f"median {_fmt(scale * e.median)} {unit} (mean infinite: {e.n_diverged} trials diverged)"


def _warn_not_converged(results) -> bool:
    failed = [r for r in results if not r.converged]
    for r in failed:
        click.echo(f"warning: the {r.controller} solve at delay {r.delay:g} s did not converge "
                   f"({r.status}): {r.message}", err=True)
    return bool(failed)


def _settings(model, noise, trials, seed, substeps) -> dict:
    return dict(model=model, noise=bool(noise), trials=int(trials), seed=int(seed), substeps=int(substeps))


# ------------------------------------------------------------------------------------------------
# commands
# ------------------------------------------------------------------------------------------------

@click.group(context_settings=dict(help_option_names=["-h", "--help"]))
@click.version_option(package_name="delayed-ilqr")
def main():
    """iLQG with control (input) delay: solve, Monte Carlo, delay studies and figures.

    Delays are given in seconds and must be whole numbers of the model's time step. Exit codes:
    0 success, 1 when a solve did not converge (results are still written), 2 for bad arguments.
    """


@main.command("models")
def models_command():
    """List the built-in models with their descriptions."""
    width = max(len(name) for name in REGISTRY)
    for name, info in REGISTRY.items():
        click.echo(f"{name.ljust(width)}  {info.description}")


@main.command("solve")
@click.argument("model", type=_MODEL, metavar="MODEL")
@click.option("--delay", type=float, default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@click.option("--noise/--no-noise", default=False, show_default=True,
              help="Solve the stochastic problem (signal-dependent noise) or the deterministic one.")
@click.option("--method", type=click.Choice(["structured", "augmented"]), default="structured", show_default=True,
              help="Backward pass: Theorem 1's structured recursion, or the state-augmentation reference.")
@click.option("--out", type=_OUT_TYPE, default=None,
              help="Folder for solution.json, solution.npz (trajectory, gains, trace) and figures.")
def solve_command(model, delay, noise, method, out):
    """Solve MODEL with iLQG and report the nominal solution and its convergence.

    MODEL is one of the names that `delayed-ilqr models` lists.
    """
    problem = _problem(model, delay, noise)
    sol, solve_time, first = study.timed_solve(problem, Options(method=method), study.default_u_init(problem))
    status = Status(int(sol.status))
    err = study.endpoint_error(problem, np.asarray(sol.x[-1])[None])[0]
    label, unit = study.endpoint_description(problem)
    scale, unit = study._unit_scale(unit)
    click.echo(_table([
        ("model", f"{model}: {REGISTRY[model].description}"),
        ("delay", f"{problem.delay:g} s ({problem.delay_steps} steps of dt = {problem.dt:g} s)"),
        ("noise", "yes" if noise else "no"),
        ("method", method),
        ("status", f"{status.name}: {status.message}"),
        ("iterations", str(int(sol.iterations))),
        ("cost (eq. 2, nominal)", _fmt(sol.cost)),
        ("expected cost (LQG)", _fmt(sol.expected_cost)),
        (f"nominal {label}", f"{_fmt(scale * err)} {unit}".rstrip()),
        ("solve time", f"{1e3 * solve_time:.1f} ms (first call with compilation: {first:.2f} s)"),
    ]))
    out = _out_dir(out)
    if out is not None:
        from . import plot
        _write_json(out / "solution.json", dict(
            model=model, delay=problem.delay, delay_steps=problem.delay_steps, dt=problem.dt, noise=bool(noise),
            method=method, converged=bool(status.converged), status=status.name, message=status.message,
            iterations=int(sol.iterations), cost=_json_float(sol.cost), expected_cost=_json_float(sol.expected_cost),
            endpoint_label=label, endpoint_error=_json_float(err), endpoint_unit=study.endpoint_description(problem)[1],
            solve_time=solve_time, first_solve_time=first))
        np.savez_compressed(out / "solution.npz", x=np.asarray(sol.x), u=np.asarray(sol.u), **_policy_arrays(sol))
        _save_figure(plot.plot_trajectories(problem, sol), out / "trajectories.png")
        _save_figure(plot.plot_convergence({model: sol}), out / "convergence.png")
        click.echo(f"wrote solution.json, solution.npz, trajectories.png, convergence.png to {out}")
    if not status.converged:
        click.echo(f"error: the solve did not converge ({status.name}): {status.message}", err=True)
        sys.exit(1)


@main.command("simulate")
@click.argument("model", type=_MODEL, metavar="MODEL")
@click.option("--delay", type=float, default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Number of Monte Carlo trials (a positive integer).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the Monte Carlo noise (the same seed gives the same trials).")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="Simulate (and design for) the stochastic plant, or the deterministic one.")
@click.option("--controller", type=click.Choice(sorted(study.CONTROLLERS)), default="aware", show_default=True,
              help="aware: designed with the delay; ignorant: designed for no delay and run on the delayed "
                   "plant; augmented: delay-aware by state augmentation.")
@click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
              help="Euler-Maruyama sub-steps per control step.")
@click.option("--out", type=_OUT_TYPE, default=None,
              help="Folder for simulate.json (summary), runs.npz (trials, nominal, gains) and figures.")
def simulate_command(model, delay, trials, seed, noise, controller, substeps, out):
    """Solve MODEL and run its feedback policy on the (noisy, delayed) plant --trials times.

    MODEL is one of the names that `delayed-ilqr models` lists.
    """
    problem = _problem(model, delay, noise)
    r = study.evaluate(problem, controller, trials, seed, substeps=substeps)
    s, c = r.summary, r.cost
    mean = f"{_fmt(c.mean)} (95% CI {_fmt(c.ci95[0])} to {_fmt(c.ci95[1])})" if math.isfinite(c.mean) \
        else f"infinite ({c.n_diverged} of {c.n} trials diverged)"
    click.echo(_table([
        ("model", f"{model}: {REGISTRY[model].description}"),
        ("delay", f"{problem.delay:g} s ({problem.delay_steps} steps of dt = {problem.dt:g} s)"),
        ("noise", "yes" if noise else "no"),
        ("controller", f"{controller}: {study.CONTROLLERS[controller]}"),
        ("solve", f"{r.status} after {r.iterations} iterations, {1e3 * r.solve_time:.1f} ms"),
        ("predicted E[J]", _fmt(r.predicted_cost)),
        ("trials", f"{c.n} (seed {seed}, {substeps} substep(s) per step)"),
        ("Monte Carlo mean J", mean),
        ("Monte Carlo median J", f"{_fmt(c.median)} (95% CI {_fmt(c.median_ci95[0])} to {_fmt(c.median_ci95[1])})"),
        (f"final {r.endpoint_label}", _endpoint_text(r)),
        ("mean final state", np.array2string(np.asarray(s.final_state_mean), precision=4)),
    ]))
    out = _out_dir(out)
    if out is not None:
        from . import plot
        _write_json(out / "simulate.json", dict(settings=dict(_settings(model, noise, trials, seed, substeps),
                                                               delay=problem.delay, controller=controller),
                                                 result=r.to_dict()))
        np.savez_compressed(out / "runs.npz", x=np.asarray(r.runs.x), u=np.asarray(r.runs.u),
                            cost=np.asarray(r.runs.cost), **_policy_arrays(r.solution))
        written = ["simulate.json", "runs.npz", "trajectories.png"]
        _save_figure(plot.plot_trajectories(problem, r.solution, r.runs), out / "trajectories.png")
        if study.arm_kinematics(problem) is not None:
            _save_figure(plot.plot_hand_paths([r]), out / "hand_paths.png")
            written.append("hand_paths.png")
        click.echo(f"wrote {', '.join(written)} to {out}")
    if _warn_not_converged([r]):
        sys.exit(1)


def _study_outputs(results, out: pathlib.Path, settings: dict, stem: str) -> list[str]:
    """Writes the JSON records, the NPZ of all trials and gains, and the figures; returns file names."""
    from . import plot
    _write_json(out / f"{stem}.json", dict(settings=settings, results=study.to_records(results)))
    arrays = {}
    for r in results:
        key = f"{r.controller}_{1e3 * r.delay:g}ms"
        arrays[f"{key}_x"] = np.asarray(r.runs.x)
        arrays[f"{key}_u"] = np.asarray(r.runs.u)
        arrays[f"{key}_cost"] = np.asarray(r.runs.cost)
        for name, value in _policy_arrays(r.solution).items():
            arrays[f"{key}_{name}"] = value
    np.savez_compressed(out / f"{stem}_runs.npz", **arrays)
    written = [f"{stem}.json", f"{stem}_runs.npz", "cost_vs_delay.png", "convergence.png"]
    _save_figure(plot.plot_delay_study(results), out / "cost_vs_delay.png")
    sols = {f"{r.controller}, {1e3 * r.delay:g} ms": r.solution for r in results if r.controller != "ignorant"}
    ignorant = [r for r in results if r.controller == "ignorant"]
    zero_aware = any(r.controller == "aware" and r.delay_steps == 0 for r in results)
    if ignorant and not zero_aware:  # the same design problem at every delay (= aware at 0 ms): one line
        sols["ignorant (designed for 0 ms)"] = ignorant[0].solution
    _save_figure(plot.plot_convergence(sols), out / "convergence.png")
    if study.arm_kinematics(results[0].problem) is not None:
        _save_figure(plot.plot_hand_paths(results), out / "hand_paths.png")
        written.append("hand_paths.png")
    return written


def _run_study(model, delays, trials, seed, noise, controllers, substeps):
    for tau in delays:                   # every delay checked before anything is solved
        _problem(model, tau, noise, hint="--delays")
    return study.compare_delays(model, delays, trials, seed, noise=noise, controllers=controllers,
                                substeps=substeps, progress=True)


@main.command("compare")
@click.argument("model", type=_MODEL, metavar="MODEL")
@click.option("--delays", type=_DelayList(), default="0,0.05,0.1", show_default=True,
              help="Comma-separated input delays in seconds, each a whole number of the model's time steps.")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the Monte Carlo noise; all controllers see the same noise samples.")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="Design for and simulate the stochastic plant, or the deterministic one.")
@click.option("--augmented/--no-augmented", default=False, show_default=True,
              help="Also evaluate the state-augmentation solution (delay-aware reference).")
@click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
              help="Euler-Maruyama sub-steps per control step.")
@click.option("--out", type=_OUT_TYPE, default=None,
              help="Folder for compare.json, compare.md, compare_runs.npz and figures.")
def compare_command(model, delays, trials, seed, noise, augmented, substeps, out):
    """Delay-aware vs delay-ignorant control of MODEL at several delays, by Monte Carlo.

    MODEL is one of the names that `delayed-ilqr models` lists. Prints one table row per delay and
    controller.
    """
    controllers = ["aware", "ignorant"] + (["augmented"] if augmented else [])
    results = _run_study(model, delays, trials, seed, noise, controllers, substeps)
    click.echo(study.format_table(results))
    out = _out_dir(out)
    if out is not None:
        settings = dict(_settings(model, noise, trials, seed, substeps), delays=list(delays), controllers=controllers)
        written = _study_outputs(results, out, settings, "compare")
        (out / "compare.md").write_text(study.format_markdown(results) + "\n")
        click.echo(f"wrote {', '.join(written + ['compare.md'])} to {out}")
    if _warn_not_converged(results):
        sys.exit(1)


_REPORT_NOTES = """\
Columns:

- **predicted E[J]**: the controller's own LQG prediction of its expected cost (`Solution.expected_cost`)
  for the plant it was designed for. The delay-ignorant controller is designed for a plant without delay,
  so it predicts the same cost at every delay.
- **MC mean J [95% CI]**: Monte Carlo mean of the cost (eq. 2) on the delayed noisy plant, with its
  normal-approximation 95 % confidence interval. It is `inf` when some trials diverged (the closed
  loop blew up); then compare the medians.
- **MC median J**: the median cost, robust to the heavy tails of nearly unstable closed loops.
- **diverged**: trials whose cost is not finite.
- **hand position error**: distance of the final hand position from the target, mean +- 1.96 standard
  errors (or the median when some trials diverged).
- **solve [ms]**: one compiled solve; **iter**: iterations; **converged**: the solver's status.

All controllers at one delay see the same noise samples (common random numbers), so their
differences are less noisy than either value.
"""


@main.command("demo")
@click.option("--out", type=_OUT_TYPE, default=pathlib.Path("out"), show_default=True,
              help="Folder for the report (report.md, report.json, report_runs.npz, figures).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the Monte Carlo noise.")
def demo_command(out, trials, seed):
    """The arm reaching study: delay-aware vs delay-ignorant iLQG on the noisy two-link arm.

    P2-noisy (models.arm2(noise=True): torque-driven arm, signal-dependent torque noise), input
    delays 0, 50 and 100 ms, --trials noisy trials per controller and delay. Prints the table and
    writes a markdown report with figures.
    """
    start = time.perf_counter()
    results = _run_study("arm2", list(DEMO_DELAYS), trials, seed, True, ["aware", "ignorant"], 1)
    elapsed = time.perf_counter() - start
    table = study.format_table(results)
    click.echo(table)
    out = _out_dir(out)
    settings = dict(_settings("arm2", True, trials, seed, 1), delays=list(DEMO_DELAYS),
                    controllers=["aware", "ignorant"], elapsed_seconds=elapsed)
    written = _study_outputs(results, out, settings, "report")
    failed = [r for r in results if not r.converged]
    lines = [
        "# Reaching with delayed commands: delay-aware vs delay-ignorant iLQG",
        "",
        f"Model: `arm2` with noise (P2-noisy): {REGISTRY['arm2'].description}; signal-dependent torque noise.",
        f"Delays: {', '.join(f'{1e3 * d:g} ms' for d in DEMO_DELAYS)}. {trials} noisy trials per controller and "
        f"delay (seed {seed}). Study time {elapsed:.1f} s (compilation included).",
        "",
        "- **aware**: " + study.CONTROLLERS["aware"],
        "- **ignorant**: " + study.CONTROLLERS["ignorant"],
        "",
        "## Results",
        "",
        study.format_markdown(results),
        "",
        _REPORT_NOTES,
    ]
    if failed:
        lines += ["## Solver warnings", ""]
        lines += [f"- {r.controller} at {1e3 * r.delay:g} ms: {r.status}: {r.message}" for r in failed]
        lines += [""]
    lines += [
        "## Figures",
        "",
        "![expected cost and endpoint error against the delay](cost_vs_delay.png)",
        "",
        "![hand paths and endpoint spread](hand_paths.png)",
        "",
        "![convergence of the solves](convergence.png)",
        "",
        "## Files",
        "",
        "- `report.json`: settings and every number of the table (non-finite values as null).",
        "- `report_runs.npz`: per controller and delay (`<controller>_<delay>ms_<name>`): trials `x`, `u`, "
        "`cost`; nominal `x_nominal`, `u_nominal`; gains `state_feedback`, `delay_feedback`, `feedforward`; "
        "solver trace `trace_*`.",
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
    click.echo(f"wrote report.md, {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if _warn_not_converged(results):
        sys.exit(1)


@main.command("center-out")
@click.option("--delays", type=_DelayList(), default=",".join(str(d) for d in DEMO_DELAYS), show_default=True,
              help="Comma-separated input delays in seconds (whole multiples of the 10 ms step).")
@click.option("--targets", "n_targets", type=click.IntRange(min=1), default=8, show_default=True,
              help="Number of targets on the circle.")
@click.option("--radius", type=click.FloatRange(min=0.0, min_open=True), default=0.1, show_default=True,
              help="Circle radius in metres around the start hand position.")
@click.option("--trials", type=click.IntRange(min=2), default=200, show_default=True,
              help="Noisy trials per target and delay.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the noise.")
@click.option("--sigma-u", type=click.FloatRange(min=0.0), default=center_out.SIGMA_U, show_default=True,
              help="Excitation noise of the plant the policies run on.")
@click.option("--design", "designs", type=click.Choice(center_out.DESIGNS), multiple=True,
              default=center_out.DESIGNS, show_default=True,
              help="Controller design, repeatable: noise-aware (iLQG, made for the noisy plant) or "
                   "deterministic (iLQR, made for the noise-free arm).")
@click.option("--max-iterations", type=click.IntRange(min=1), default=center_out.DEFAULT_OPTIONS.max_iterations,
              show_default=True, help="Iteration limit of each reach's solve.")
@click.option("--allow-unconverged", is_flag=True,
              help="Exit 0 even when some reaches did not converge (they are flagged in the table and on stderr).")
@click.option("--out", type=_OUT_TYPE, default=None, help="Folder for center_out.md/.json and the figures.")
def center_out_command(delays, n_targets, radius, trials, seed, sigma_u, designs, max_iterations, allow_unconverged,
                       out):
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
    start = time.perf_counter()
    options = dataclasses.replace(center_out.DEFAULT_OPTIONS, max_iterations=max_iterations)
    results = center_out.center_out(delays, n_targets, radius, trials, seed, options=options, sigma_u=sigma_u,
                                    designs=designs)
    elapsed = time.perf_counter() - start
    table = center_out.format_table(results)
    click.echo(table)
    if out is not None:
        out = _out_dir(out)
        from . import plot
        _save_figure(plot.plot_center_out(results), out / "center_out_hand_paths.png")
        figures = ["center_out_hand_paths.png"]
        for r in results:
            name = f"center_out_excitations_{r.design}_{1e3 * r.delay:g}ms.png"
            _save_figure(plot.plot_excitations(r), out / name)
            figures.append(name)
        settings = dict(delays=list(delays), targets=n_targets, radius=radius, trials=trials, seed=seed,
                        sigma_u=sigma_u, designs=list(designs), max_iterations=max_iterations,
                        elapsed_seconds=elapsed)
        _write_json(out / "center_out.json", dict(settings=settings, results=center_out.to_records(results)))
        lines = ["# Center-out reaching, six-muscle arm, delayed excitations", "",
                 f"{n_targets} targets at {1e3 * radius:g} mm, {trials} noisy trials per target (sigma_u "
                 f"{sigma_u:g}, seed {seed}); designs: {', '.join(designs)}. Study time {elapsed:.1f} s.", "",
                 table, ""] + [f"![{f}]({f})" for f in figures] + [""]
        (out / "center_out.md").write_text("\n".join(lines))
        click.echo(f"wrote center_out.md, center_out.json, {', '.join(figures)} to {out} ({elapsed:.1f} s)")
    failed = [(r.delay, r.design, j) for r in results for j, t in enumerate(r.targets) if not t.converged]
    for delay, design, j in failed:
        click.echo(f"warning: the {design} reach to target {j + 1} at delay {delay:g} s did not converge", err=True)
    if failed and not allow_unconverged:
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    main()
