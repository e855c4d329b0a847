"""The report writer: JSON records, NPZ arrays, markdown documents and figures on disk.

Everything a command writes into its ``--out`` folder is built here from the engine's results and
the strings of `tables`; the figures come from [`delayed_ilqr.plot`][delayed_ilqr.plot] (made by the
caller, saved by `save_figures`).
"""
from __future__ import annotations

import math
import pathlib
from typing import Mapping, Sequence

import numpy as np

from .. import Status, _files
from .delay_study import ControllerResult
from .designs import REGISTRY
from .delay_text import delay_tag, delay_text
from .records import delay_values, problem_record
from .tables import delay_study_rows, delay_study_warnings, markdown_table

__all__ = ["DESCRIPTIONS", "DPI", "json_ready", "write_json", "save_figures", "policy_arrays", "delay_study_records",
           "center_out_records",
           "write_solution", "write_runs", "write_delay_study", "write_demo_report", "write_center_out_report"]

DPI = 120  # resolution of every saved figure

#: What the cost keys of the JSON records mean; every study's JSON carries it as ``descriptions``.
DESCRIPTIONS = {
    "predicted_cost": "the local (linearised) prediction of E[J]: Solution.expected_cost, J(0) of the LQG "
                      "approximation at the nominal; exact for the linearised plant only (the Monte Carlo is the "
                      "measurement)",
    "expected_cost": "the local (linearised) prediction of E[J] (Solution.expected_cost), as predicted_cost",
    "cost": "eq. (2) on the noise-free nominal (solution) or SampleStats of the Monte Carlo cost per trial "
            "(study records): mean over the trials that did not diverge with its bootstrap ci95, median over all",
    "mc_cost": "SampleStats of the Monte Carlo cost per trial: mean over the trials that did not diverge with its "
               "bootstrap ci95, median over all trials (diverged as +inf)",
}


def write_json(path: pathlib.Path, data) -> None:
    """Strict JSON (non-finite numbers must already be ``None``), indented, written atomically."""
    _files.write_json(path, data)


def json_ready(value):
    """``value`` as strict JSON data: non-finite floats become None (null), NumPy and JAX arrays and
    scalars plain lists and numbers, dicts, lists and tuples converted item by item, and an object with a
    ``to_dict`` (e.g. [`SampleStats`][delayed_ilqr.statistics.SampleStats]) by its dict; anything else
    is returned as it is."""
    if hasattr(value, "to_dict"):              # SampleStats (a NamedTuple: before the tuples)
        return json_ready(value.to_dict())
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if hasattr(value, "shape") and hasattr(value, "dtype"):       # NumPy and JAX arrays and scalars
        array = np.asarray(value)
        return json_ready(array.tolist() if array.ndim else array.item())
    return value


def save_figures(figures: Mapping[str, object], out: pathlib.Path) -> list[str]:
    """Saves ``{file name: Figure}`` into ``out`` (each atomically); returns the file names."""
    for name, fig in figures.items():
        _files.save_figure(fig, out / name, dpi=DPI)
    return list(figures)


def policy_arrays(sol) -> dict:
    """The nominal, the gains and the solver trace of a solution, by NPZ name (with sensors also
    the filter: ``estimator_<field>`` for each array of [`Estimator`][delayed_ilqr.Estimator] and
    ``estimator_sensory_delay``)."""
    p, t = sol.policy, sol.trace
    n = int(sol.iterations) + 1
    arrays = dict(x_nominal=np.asarray(p.x_nominal), u_nominal=np.asarray(p.u_nominal),
                  feedforward=np.asarray(p.feedforward), state_feedback=np.asarray(p.state_feedback),
                  delay_feedback=np.asarray(p.delay_feedback), trace_cost=np.asarray(t.cost[:n]),
                  trace_merit=np.asarray(t.merit[:n]), trace_step_size=np.asarray(t.step_size[:n]),
                  trace_reg=np.asarray(t.reg[:n]), trace_grad_norm=np.asarray(t.grad_norm[:n]))
    if p.estimator is not None:
        for name in p.estimator._arrays:
            arrays[f"estimator_{name}"] = np.asarray(getattr(p.estimator, name))
        arrays["estimator_sensory_delay"] = np.asarray(p.estimator.sensory_delay)
    return arrays


def delay_study_records(results: Sequence[ControllerResult]) -> list[dict]:
    """``[r.to_dict() for r in results]``: JSON-ready records."""
    return [r.to_dict() for r in results]


def center_out_records(results: Sequence) -> list[dict]:
    """Every number of the center-out study as JSON-ready dicts (one per delay and design, with a
    list of targets; the statistical design's targets add ``sl_change``, SL's last relative feedback
    change); the delay as `records.delay_values` writes it."""
    return [dict(zip(("delay", "delay_steps"), delay_values(r.plants[0])), dt=r.dt, design=r.design,
                 solve_time=r.solve_time, first_call=r.first_call,
                 targets=[dict(target=t.target.tolist(), status=t.status, iterations=t.iterations, cost=t.cost,
                               predicted_cost=t.predicted_cost, mc_cost=t.cost_stats.to_dict(),
                               hand_error=t.hand_error, hand_speed=t.hand_speed, mc_error=t.error_stats.to_dict(),
                               endpoint_mean=json_ready(t.endpoints[~t.diverged].mean(axis=0)),
                               endpoint_cov=[json_ready(row) for row in t.endpoint_cov], spread=json_ready(t.spread),
                               **({} if t.sl_change is None else dict(sl_change=json_ready(t.sl_change))))
                          for t in r.targets])
            for r in results]


def write_solution(out: pathlib.Path, model: str, problem, method: str, timed, endpoint) -> list[str]:
    """The ``solve`` command's solution.json (settings, status, costs, endpoint error, timing, the
    problem's record, `records.problem_record`) and solution.npz (the
    [`Solution`][delayed_ilqr.Solution]: trajectory, gains, trace, in the format of
    [`delayed_ilqr.saving`][delayed_ilqr.saving], so that ``delayed_ilqr.load`` reads it; the record is in its
    header's ``info``); ``timed`` and ``endpoint`` as in `tables.solve_summary`."""
    sol, solve_time, first = timed
    status = Status(int(sol.status))
    label, unit, value = endpoint
    record = problem_record(problem)
    write_json(out / "solution.json", dict(
        descriptions={"expected_cost": DESCRIPTIONS["expected_cost"]}, model=model, delay=record["delay"],
        delay_steps=record["delay_steps"], dt=problem.dt,
        noise=problem.noise is not None, method=method, converged=bool(status.converged), status=status.name,
        message=status.message, iterations=int(sol.iterations), cost=json_ready(sol.cost),
        expected_cost=json_ready(sol.expected_cost), endpoint_label=label, endpoint_error=json_ready(value),
        endpoint_unit=unit, solve_time=solve_time, first_solve_time=first, problem=record))
    sol.save(out / "solution.npz", problem, info=dict(model=model, method=method, problem=record))
    return ["solution.json", "solution.npz"]


def _descriptions(*keys) -> dict:
    return {k: DESCRIPTIONS[k] for k in keys}


def write_runs(out: pathlib.Path, result: ControllerResult, settings: dict) -> list[str]:
    """The ``simulate`` command's simulate.json (settings and the result's record), runs.npz
    (trials, nominal, gains, trace) and solution.npz (the solution whose policy ran, readable by
    ``delayed_ilqr.load``)."""
    write_json(out / "simulate.json", dict(settings=settings, result=result.to_dict()))
    _files.savez(out / "runs.npz", dict(x=np.asarray(result.runs.x), u=np.asarray(result.runs.u),
                                        cost=np.asarray(result.runs.cost), **policy_arrays(result.solution)),
                 compressed=True)
    result.solution.save(out / "solution.npz", result.problem, info=settings)
    return ["simulate.json", "runs.npz", "solution.npz"]


def write_delay_study(results: Sequence[ControllerResult], out: pathlib.Path, settings: dict, stem: str) -> list[str]:
    """``<stem>.json`` (settings and every number of the table) and ``<stem>_runs.npz`` (per
    controller and delay ``<controller>_<delay>_<name>``, the delay as `delay_text.delay_tag` writes
    it, e.g. ``aware_50ms_x``: trials, nominal, gains, trace)."""
    write_json(out / f"{stem}.json", dict(settings=settings, descriptions=_descriptions("predicted_cost", "cost"),
                                          warnings=delay_study_warnings(results),
                                          results=delay_study_records(results)))
    arrays = {}
    for r in results:
        key = f"{r.controller}_{delay_tag(r.problem)}"
        arrays[f"{key}_x"] = np.asarray(r.runs.x)
        arrays[f"{key}_u"] = np.asarray(r.runs.u)
        arrays[f"{key}_cost"] = np.asarray(r.runs.cost)
        for name, value in policy_arrays(r.solution).items():
            arrays[f"{key}_{name}"] = value
    _files.savez(out / f"{stem}_runs.npz", arrays, compressed=True)
    return [f"{stem}.json", f"{stem}_runs.npz"]


_DEMO_NOTES = """\
Columns:

- **local prediction E[J] (linearised)**: the controller's own LQG prediction of its expected cost
  (`Solution.expected_cost`) for the plant it was designed for, exact only for the linearised plant.
  The delay-ignorant controller is designed for a plant without delay, so it predicts the same cost
  at every delay. A study warns (below, and on stderr) where the Monte Carlo mean departs from it by
  more than 2x either way.
- **MC mean J [95% CI]**: Monte Carlo mean of the cost (eq. 2) on the delayed noisy plant over the
  trials that did not diverge, with its seeded bootstrap 95 % interval (never below the smallest cost).
- **MC median J [IQR]**: the median cost over all trials (a diverged trial ranks last) and its
  inter-quartile range, robust to the heavy tails of nearly unstable closed loops.
- **diverged**: trials whose cost is not finite or above 100 times the cost of not moving at all
  (all commands zero): the closed loop lost control. One definition (`delayed_ilqr.statistics`)
  for this table, both panels of the figures and the JSON.
- **hand position error**: distance of the final hand position from the target, over the same
  trials: mean [95 % interval] and median [IQR].
- **solve [ms]**: one compiled solve; **iter**: iterations; **converged**: the solver's status.

All controllers at one delay see the same noise samples (common random numbers), so their
differences are less noisy than either value.
"""

_DEMO_FILES = """\
## Figures

![expected cost, endpoint error and endpoint spread against the delay](cost_vs_delay.png)

Monte Carlo mean cost with its bootstrap 95 % interval and each controller's local (linearised) prediction E[J]; the
mean distance of the final hand position from the target; the spread of the final hand positions
(1-sigma major axis). Compared with: human endpoint scatter of a few millimetres for unseen
reaches (Gordon, Ghilardi & Ghez 1994, Exp Brain Res 99:97). This plant has no sensory noise or
sensory delay, so at no delay its scatter is far smaller (docs/results/noise_calibration.md).

![hand paths, hand speed and endpoints](hand_paths.png)

Top: nominal hand paths (thick) and ten noisy trials (thin). Middle: hand speed against time.
Bottom: endpoints relative to the target (mm) with 2-sigma ellipses. Compared with: human reaches
run along nearly straight paths with single-peaked, bell-shaped speed profiles (Morasso 1981, Exp
Brain Res 42:223; Flash & Hogan 1985, J Neurosci 5:1688). The P2 task (docs/models.md §2)
weighs effort and the final state only: its paths curve and its speed profile at no delay is
flat-topped; with delay the delay-aware reach starts one delay late, with a higher, earlier peak.

![convergence of the solves](convergence.png)

The cost of the nominal at each iteration of every solve (open markers: rejected steps; dashed:
the noise-aware merit).

## Files

- `report.json`: settings and every number of the table (non-finite values as null).
- `report_runs.npz`: per controller and delay (`<controller>_<delay>ms_<name>`): trials `x`, `u`, `cost`; \
nominal `x_nominal`, `u_nominal`; gains `state_feedback`, `delay_feedback`, `feedforward`; solver trace `trace_*`.
"""


def write_demo_report(out: pathlib.Path, results: Sequence[ControllerResult], description: str,
                      delays: Sequence[float], trials: int, seed: int, elapsed: float) -> str:
    """The demo's report.md: the setting, the table, the notes on its columns, solver warnings,
    figures and files; returns the file name."""
    lines = [
        "# Reaching with delayed commands: delay-aware vs delay-ignorant iLQG",
        "",
        f"Model: `arm2` (the P2 reach): {description}; signal-dependent torque noise at the human level "
        "(sigma_u = 0.01, calibrated to human force variability, docs/models.md §4.5).",
        f"Delays: {', '.join(delay_text(d) for d in delays)}. {trials} noisy trials per controller and "
        f"delay (seed {seed}). Study time {elapsed:.1f} s (compilation included).",
        "",
        "- **aware**: " + REGISTRY["aware"].description,
        "- **ignorant**: " + REGISTRY["ignorant"].description,
        "",
        "## Results",
        "",
        markdown_table(delay_study_rows(results)),
        "",
        _DEMO_NOTES,
    ]
    warned = delay_study_warnings(results)
    if warned:
        lines += ["## Warnings", ""] + [f"- {w}" for w in warned] + [""]
    failed = [r for r in results if not r.converged]
    if failed:
        lines += ["## Solver warnings", ""]
        lines += [f"- {r.controller} at {delay_text(r.problem)}: {r.status}: {r.message}" for r in failed]
        lines += [""]
    _files.write_text(out / "report.md", "\n".join(lines) + "\n" + _DEMO_FILES)
    return "report.md"


def _caption(file_name: str) -> str:
    """The caption of a center-out figure (`delayed_ilqr.plot.CAPTIONS`, by name or prefix)."""
    from ..plot import CAPTIONS
    for key, caption in CAPTIONS.items():
        if file_name == key or file_name.startswith(key + "_"):
            return caption
    return ""


_STATISTICAL_NOTE = (
    "*statistical*: the noise-aware design with its feedback gains re-designed by statistical linearisation "
    "around the closed loop's predicted distribution (`delayed_ilqr.statistical.statistical_feedback`: "
    "fifth-degree rule, 8 iterations, relaxation 0.5; docs/results/noise_calibration.md §5.5). Its converged, "
    "iterations and nominal columns are the noise-aware solve's; its solve time adds the SL re-design; its "
    "predicted E[J] is the Gaussian closure's for the SL gains (the solver has no LQG prediction for them). "
    "center_out.json gives each target's `sl_change`, SL's last relative feedback change (near 0 at a "
    "fixed point).")


def write_center_out_report(out: pathlib.Path, results: Sequence, settings: dict, table: str,
                            figures: Sequence[str]) -> list[str]:
    """center_out.json (settings and every number) and center_out.md (setting, table, figures)."""
    from .tables import center_out_warnings
    write_json(out / "center_out.json", dict(settings=settings, descriptions=_descriptions("predicted_cost", "mc_cost"),
                                             warnings=center_out_warnings(results),
                                             results=center_out_records(results)))
    s = settings
    lines = ["# Center-out reaching, six-muscle arm, delayed excitations", "",
             f"{s['targets']} targets at {1e3 * s['radius']:g} mm, {s['trials']} noisy trials per target (sigma_u "
             f"{s['sigma_u']:g}, seed {s['seed']}); designs: {', '.join(s['designs'])}; "
             + ("the controllers see the state" if s.get("sensory_delay") is None else
                f"the controllers see proprioception {1e3 * s['sensory_delay']:g} ms late through a delayed "
                "Kalman filter")
             + f". Study time {s['elapsed_seconds']:.1f} s.", "",
             table, ""]
    if "statistical" in s["designs"]:
        lines += [_STATISTICAL_NOTE, ""]
    for f in figures:
        lines += [f"![{f}]({f})", "", _caption(f), ""]
    _files.write_text(out / "center_out.md", "\n".join(lines))
    return ["center_out.md", "center_out.json"]
