"""A delay as the reports, figures and tables write it (experiments/delay_text.py), and every
report, figure and table entry point fed a per-channel, a fractional and a jittered problem.

The expected texts are the specification (one delay "50 ms", per channel "[50, 70] ms", a delay
between steps as its exact value, a jitter with its distribution), not output read back. The
results are synthetic (no solve): the entry points only format them. `evaluate` builds its
results' delays with `records.delay_values`, which the fakes call the same way; the full-size
version (a real study of per-channel and fractional problems, written to disk) is marked `full`.
"""
import json
from types import SimpleNamespace

import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import plot
from delayed_ilqr.experiments import fitts, mpc_baselines, report, tables
from delayed_ilqr.experiments.center_out import DelayResult, TargetResult
from delayed_ilqr.experiments.delay_study import ControllerResult
from delayed_ilqr.experiments.delay_text import (delay_axis, delay_key, delay_tag, delay_text, milliseconds,
                                                 seconds)
from delayed_ilqr.experiments.reach_tasks import loop_latency
from delayed_ilqr.experiments.records import delay_values
from delayed_ilqr.models import arm2, arm2_muscle6, point_mass
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV
from delayed_ilqr.simulate import Runs
from delayed_ilqr.statistics import sample_stats, summarize

N_TRIALS = 12
JITTER = di.DelayJitter([2, 3, 4], [0.25, 0.5, 0.25])


@pytest.fixture(scope="module")
def plants():
    """The arm at one delay (100 ms), per channel (50 and 70 ms), between steps (25 ms = 2.5
    steps; 25 and 33.3 ms per channel) and jittered (20, 30 or 40 ms), with the texts expected."""
    base = arm2(delay=0.05, noise="benchmark")
    return {
        "one": (arm2(delay=0.1, noise="benchmark"), "100 ms", "100 ms (10 steps of dt = 10 ms)", "100ms"),
        "per-channel": (base.replace(delay_steps=[5, 7]), "[50, 70] ms", "[50, 70] ms ([5, 7] steps of dt = 10 ms)",
                        "50,70ms"),
        "fractional": (arm2(delay=0.025, noise="benchmark"), "25 ms", "25 ms (2.5 steps of dt = 10 ms)", "25ms"),
        "fractional per channel": (base.replace(delay_steps=[2.5, 10 / 3]), "[25, 33.333333] ms",
                                   "[25, 33.333333] ms ([2.5, 3.333333] steps of dt = 10 ms)", "25,33.333333ms"),
        "jittered": (base.replace(delay_steps=4, delay_jitter=JITTER), "20/30/40 ms jittered (p = 0.25/0.5/0.25)",
                     "20/30/40 ms jittered (p = 0.25/0.5/0.25) (2/3/4 steps of dt = 10 ms)", "jitter20,30,40ms"),
    }


ODD = ("per-channel", "fractional", "fractional per channel", "jittered")


def test_the_text_of_every_kind_of_delay(plants):
    for name, (problem, text, with_steps, tag) in plants.items():
        assert delay_text(problem) == text and delay_text(problem, steps=True) == with_steps, name
        assert delay_tag(problem) == tag, name
    # seconds: floating-point round-off is not written (1e3 * 0.07 = 70.00000000000001)
    assert [delay_text(s) for s in (0.0, 0.07, 0.0255, [0.05, 0.07], (0.03, 0.03))] == \
        ["0 ms", "70 ms", "25.5 ms", "[50, 70] ms", "30 ms"]
    assert milliseconds([0.05, 0.07]) == (50.0, 70.0) and seconds(plants["fractional"][0]) == 0.025
    with pytest.raises(TypeError, match="delay_text.*needs a delayed_ilqr.Problem"):
        delay_text(0.05, steps=True)
    with pytest.raises(TypeError, match="delay must be a delayed_ilqr.Problem or seconds"):
        delay_text("50 ms")


def test_a_delay_axis_in_ms_or_by_rank(plants):
    one, fractional = plants["one"][0], plants["fractional"][0]
    positions, ticks, label = delay_axis([one, fractional, 0.0])
    np.testing.assert_array_equal(positions, [100.0, 25.0, 0.0])
    assert ticks is None and label == "input delay [ms]"
    per_channel, jittered = plants["per-channel"][0], plants["jittered"][0]
    positions, ticks, label = delay_axis([one, per_channel, jittered, fractional, per_channel])
    # in order of the longest channel: 25, 40 (jittered), 70 ([50, 70]), 100 ms
    np.testing.assert_array_equal(positions, [3, 2, 1, 0, 2])
    assert ticks == ([0, 1, 2, 3], ["25 ms", plants["jittered"][1], "[50, 70] ms", "100 ms"]) and label == "input delay"
    assert delay_key(jittered) != delay_key(plants["one"][0].replace(delay_steps=4))


# --------------------------------------------------------------------------------------------
# The delay study: tables, warnings, summaries, files and figures
# --------------------------------------------------------------------------------------------
def _solution(problem):
    """A Solution of the problem's shapes (a straight nominal, zero gains, a three-step trace)."""
    K, n, d = problem.horizon, problem.n_states, problem.n_controls
    target = np.asarray(problem.cost.x_target)
    x = np.asarray(problem.x0)[None] + np.linspace(0.0, 1.0, K + 1)[:, None] * (target - np.asarray(problem.x0))
    u = np.zeros((K, d))
    policy = di.Policy(x, u, u, np.zeros((K, d, n)), np.zeros((K, problem.frame_steps, d, d)))
    trace = di.Trace(cost=np.array([3.0, 2.0, 1.0]), merit=np.array([3.0, 2.0, 1.0]), expected_reduction=np.zeros(3),
                     step_size=np.array([np.nan, 1.0, 1.0]), reg=np.zeros(3), grad_norm=np.zeros(3))
    return di.Solution(x=x, u=u, cost=1.0, expected_cost=1.0, status=np.int32(1), iterations=np.int32(2),
                       policy=policy, trace=trace)


def fake_result(problem, controller="aware", predicted=1.0, converged=True):
    """A ControllerResult as `delay_study.evaluate` builds it, from synthetic runs."""
    sol = _solution(problem)
    rng = np.random.default_rng(len(controller))
    x = np.asarray(sol.x)[None] + 0.01 * rng.standard_normal((N_TRIALS, 1, problem.n_states))
    runs = Runs(x=x, u=np.zeros((N_TRIALS, problem.horizon, problem.n_controls)), cost=1.0 + rng.random(N_TRIALS))
    cost = sample_stats(np.asarray(runs.cost))
    delay, delay_steps = delay_values(problem)
    return ControllerResult(
        model=problem.name, delay=delay, delay_steps=delay_steps, noise=True, controller=controller,
        converged=converged, status="CONVERGED_COST" if converged else "MAX_ITERATIONS", message="",
        iterations=2, solve_time=0.01, first_solve_time=1.0, nominal_cost=1.0, predicted_cost=predicted, cost=cost,
        endpoint_error=sample_stats(1e-3 * rng.random(N_TRIALS)), divergence_bound=np.inf,
        endpoint_label="hand position error", endpoint_unit="m", summary=summarize(runs.cost, x[:, -1]),
        n_trials=N_TRIALS, seed=0, substeps=1, problem=problem, solution=sol, runs=runs)


@pytest.mark.parametrize("name", ODD)
def test_delay_study_tables_warnings_and_summaries(plants, name):
    problem, text, with_steps, _ = plants[name]
    results = [fake_result(problem, predicted=100.0), fake_result(plants["one"][0], "ignorant")]
    header, rows = tables.delay_study_rows(results)
    assert header[0] == "delay" and [row[0] for row in rows] == [text, "100 ms"]
    # the Monte Carlo mean (about 1.5) is far below the prediction of 100: a warning naming the delay
    assert tables.delay_study_warnings(results)[0].startswith(f"warning: arm2, aware at {text}: ")
    assert dict(tables.simulate_summary(results[0], "the arm"))["delay"] == with_steps
    timed = (_solution(problem), 0.01, 1.0)
    assert dict(tables.solve_summary(problem, "the arm", True, "structured", timed, ("error", "m", 0.001)))["delay"] \
        == with_steps


@pytest.mark.parametrize("name", ODD)
def test_delay_study_files(plants, name, tmp_path):
    problem, text, _, tag = plants[name]
    results = [fake_result(problem), fake_result(plants["one"][0], converged=False)]
    written = report.write_delay_study(results, tmp_path, {}, "compare")
    record = json.loads((tmp_path / written[0]).read_text())["results"][0]
    delay, steps = delay_values(problem)
    assert (record["delay"], record["delay_steps"]) == (delay, steps)
    if name == "fractional":
        assert steps == [2.5, 2.5]                     # l + phi per channel, not the taps [2, 2, 3, 3]
    with np.load(tmp_path / written[1]) as npz:
        assert npz[f"aware_{tag}_x"].shape == (N_TRIALS, problem.horizon + 1, 4)
        assert npz[f"aware_{tag}_delay_feedback"].shape[1] == problem.frame_steps
    report.write_demo_report(tmp_path, results[::-1], "the arm", [0.1, 0.025], N_TRIALS, 0, 1.0)
    demo = (tmp_path / "report.md").read_text()
    assert "Delays: 100 ms, 25 ms." in demo and f"| {text} | aware |" in demo
    assert "- aware at 100 ms: MAX_ITERATIONS" in demo          # the solver warnings name the delay too


@pytest.mark.parametrize("name", ODD)
def test_delay_study_figures(plants, name):
    problem, text, _, _ = plants[name]
    one = plants["one"][0]
    results = [fake_result(problem), fake_result(problem, "ignorant"), fake_result(one), fake_result(one, "ignorant")]
    figures = plot.delay_study_figures(results)
    ax = figures["cost_vs_delay.png"].axes[0]
    if name == "fractional":                       # one number: on the axis in ms
        assert ax.get_xlabel() == "input delay [ms]"
        # the two controllers side by side, +-0.6 x 4 % of the 75 ms between the delays
        np.testing.assert_allclose(sorted(x for c in ax.containers for x in c.lines[0].get_xdata()),
                                   [23.2, 26.8, 98.2, 101.8], rtol=1e-12)
    else:                                          # by rank, each tick named by its delay
        assert ax.get_xlabel() == "input delay"
        assert [t.get_text() for t in ax.get_xticklabels()] == [text, "100 ms"]
        np.testing.assert_allclose(np.round(sorted(x for c in ax.containers for x in c.lines[0].get_xdata())),
                                   [0, 0, 1, 1])
    paths = figures["hand_paths.png"]
    assert [paths.axes[i].get_title() for i in (0, 1, 4)] == [f"{text}: hand paths", "100 ms: hand paths",
                                                              f"{text}: endpoints (N = {N_TRIALS})"]
    legend = [t.get_text() for t in figures["convergence.png"].axes[0].get_legend().get_texts()]
    assert f"aware, {text}: cost (converged)" in legend and "aware, 100 ms: cost (converged)" in legend
    trajectories = plot.plot_trajectories(problem, results[0].solution)
    assert f"(acting {text} later)" in trajectories._suptitle.get_text()


def test_an_unconverged_solve_names_its_delay(plants, capsys):
    from delayed_ilqr.cli.output import warn_not_converged
    assert warn_not_converged([fake_result(plants["per-channel"][0], converged=False)])
    assert "the aware solve at delay [50, 70] ms did not converge" in capsys.readouterr().err


def test_a_sweep_table_writes_its_grid_delays_as_delays():
    """A sweep over delays in seconds: one delay between steps (25.5 ms, not "0.0255"), and a
    user's factory argument with one delay per channel (its ``delay_value`` components)."""
    xr = pytest.importorskip("xarray")
    dims = ("delay", "seed")
    data = dict(status=(("delay",), np.array([0, 0])), iterations=(("delay",), np.array([4, 5])),
                expected_cost=(("delay",), np.array([1.0, 1.0])),
                mc_cost_mean=(dims, np.ones((2, 1))), mc_cost_ci_low=(dims, np.ones((2, 1))),
                mc_cost_ci_high=(dims, np.ones((2, 1))), mc_cost_median=(dims, np.ones((2, 1))),
                mc_diverged=(dims, np.zeros((2, 1))), mc_endpoint_error_median=(dims, np.ones((2, 1)), {"units": "m"}))
    ds = xr.Dataset(data, coords=dict(delay=("delay", [0.0255, 0.1], {"units": "s"})), attrs=dict(trials=10))
    assert [row[0] for row in tables.sweep_rows(ds)[1]] == ["25.5 ms", "100 ms"]
    per_channel = xr.Dataset(data, coords=dict(
        delay=("delay", [0, 1]), delay_value=(("delay", "delay_component"), [[0.05, 0.07], [0.1, 0.1]], {"units": "s"})),
        attrs=dict(trials=10))
    assert [row[0] for row in tables.sweep_rows(per_channel)[1]] == ["[50, 70] ms", "100 ms"]


# --------------------------------------------------------------------------------------------
# Center-out (a fractional delay: the study takes one delay in seconds), the gallery, MPC
# --------------------------------------------------------------------------------------------
def test_center_out_at_a_delay_between_steps(tmp_path):
    """25.5 ms on the 10 ms grid: the table, the figures' titles and file names, the records."""
    n_trials = 6
    plants = [arm2_muscle6(**LI_TODOROV, delay=0.0255, target=(-0.02 + 0.1 * np.cos(a), 0.45 + 0.1 * np.sin(a)))
              for a in (0.0, 2.0)]
    rng = np.random.default_rng(0)
    targets = []
    for plant in plants:
        target = np.asarray(plant.cost.params["target"])
        ends = target + 1e-3 * rng.standard_normal((n_trials, 2))
        targets.append(TargetResult(target=target, status="CONVERGED_COST", iterations=10, cost=1.0,
                                    predicted_cost=100.0, hand_error=1e-4, hand_speed=1e-3, endpoints=ends,
                                    mc_error=np.linalg.norm(ends - target, axis=1), mc_cost=1.0 + rng.random(n_trials),
                                    diverged=np.zeros(n_trials, bool)))
    x = np.repeat(np.asarray(plants[0].x0)[None, None], plants[0].horizon + 1, axis=1).repeat(2, axis=0)
    result = DelayResult(delay=0.0255, delay_steps=plants[0].delay_steps, dt=0.01, design="noise-aware", solve_time=0.1,
                         first_call=1.0, targets=targets, solutions=SimpleNamespace(x=x, u=rng.random((2, 50, 6))),
                         runs=[SimpleNamespace(x=x[j][None].repeat(n_trials, axis=0)) for j in range(2)], plants=plants)
    assert tables.center_out_rows([result])[1][0][0] == "25.5 ms"
    assert tables.center_out_warnings([result])[0].startswith("warning: noise-aware at 25.5 ms, targets 1, 2 of 2")
    figures = plot.center_out_figures([result])
    assert "center_out_excitations_noise-aware_25.5ms.png" in figures
    assert figures["center_out_hand_paths.png"].axes[0].get_title().startswith("noise-aware, 25.5 ms")
    assert figures["center_out_excitations_noise-aware_25.5ms.png"]._suptitle.get_text().endswith("delay 25.5 ms")
    record = report.center_out_records([result])[0]
    assert record["delay"] == pytest.approx([0.0255] * 6, rel=1e-12)
    assert record["delay_steps"] == pytest.approx([2.55] * 6, rel=1e-12)   # l + phi, not the taps [2, 3]


def test_gallery_and_loop_latency_at_a_delay_between_steps():
    """Fitts' comparison rows and legend at 25.5 ms (not rounded to 26); the loop latency of a
    plant whose motor delay is between steps, per channel or jittered: its earliest response."""
    ds, ws = np.array([0.04, 0.08]), np.array([0.01, 0.02])
    index = np.log2(2 * ds[:, None] / ws[None, :])
    result = fitts.FittsResult(0.0255, None, ds, ws, np.array([0.2, 0.3]), np.zeros((2, 2)), np.ones((2, 2)), None,
                               0.1 + 0.15 * index, index, None, np.ones((2, 2)), np.ones((2, 2)), None)
    assert fitts.comparison([result])[0]["finding"] == "motor delay 25.5 ms"
    from delayed_ilqr.plot.gallery import plot_fitts
    legend = plot_fitts([result]).axes[0].get_legend_handles_labels()[1]
    assert any(label.startswith("motor delay 25.5 ms") for label in legend), legend
    base = point_mass(delay=0.05)
    assert loop_latency(point_mass(delay=0.0255)) == pytest.approx(0.0255, rel=1e-12)
    assert loop_latency(base.replace(delay_steps=[3, 5])) == pytest.approx(0.03, rel=1e-12)
    assert loop_latency(base.replace(delay_steps=4, delay_jitter=JITTER)) == pytest.approx(0.02, rel=1e-12)


def test_the_mpc_table_of_a_per_channel_model(plants):
    """The rows `mpc_baselines.compare` makes of a model with per-channel delays ([50, 70] ms)."""
    row = mpc_baselines.Row("arm2", milliseconds(plants["per-channel"][0]), "plant", "in-flight", 1.0, 0.0, 0.001, "m")
    assert "| [50, 70] ms | plant |" in mpc_baselines.markdown([row], ["in-flight"])
    assert json.loads(json.dumps(row._asdict()))["delay_ms"] == [50.0, 70.0]


@pytest.mark.full
def test_a_study_of_per_channel_and_fractional_problems_on_disk(tmp_path):
    """The real thing (solves and Monte Carlo): `compare_delays` over a factory that gives the point
    mass per-channel (10 and 30 ms) and fractional (25 ms) delays, its tables, files and figures."""
    from delayed_ilqr.experiments.delay_study import compare_delays

    def factory(delay, noise):
        problem = point_mass(noise=noise, horizon=20)
        return problem.replace(delay_steps=[1, 3] if delay == 0.01 else 2.5)

    results = compare_delays(factory, [0.01, 0.02], n_trials=20)
    assert [r.delay for r in results] == [[0.01, 0.03]] * 2 + [[0.025, 0.025]] * 2
    text = tables.text_table(tables.delay_study_rows(results))
    assert "[10, 30] ms" in text and "25 ms" in text
    report.write_delay_study(results, tmp_path, {}, "compare")
    report.save_figures(plot.delay_study_figures(results), tmp_path)
    assert {p.name for p in tmp_path.iterdir()} >= {"compare.json", "compare_runs.npz", "cost_vs_delay.png"}
