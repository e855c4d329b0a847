"""Figures: each function returns a Figure with the documented axes and lines, and saves to PNG.

The inputs are synthetic (no solve, no compilation): the plot functions only read arrays.
"""
import dataclasses
import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.image import imread
from matplotlib.patches import Ellipse

import delayed_ilqr as di
from delayed_ilqr import plot
from delayed_ilqr.experiments.delay_study import ControllerResult
from delayed_ilqr.experiments.engine import endpoint_error
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.simulate import Runs
from delayed_ilqr.statistics import sample_stats, summarize

N_TRIALS = 40


def synthetic_runs(problem, x_nominal, u_nominal, spread, seed):
    rng = np.random.default_rng(seed)
    K = problem.horizon
    ramp = np.linspace(0.0, 1.0, K + 1)[None, :, None]
    x = x_nominal[None] + spread * ramp * rng.standard_normal((N_TRIALS, 1, problem.n_states))
    u = u_nominal[None] + 0.1 * rng.standard_normal((N_TRIALS, K, problem.n_controls))
    cost = 1.0 + spread * rng.chisquare(2, N_TRIALS)
    return Runs(x=x, u=u, cost=cost)


def nominal(problem):
    K = problem.horizon
    target = np.asarray(problem.cost.x_target)
    x = np.asarray(problem.x0)[None] + np.linspace(0.0, 1.0, K + 1)[:, None] * (target - np.asarray(problem.x0))
    u = np.sin(np.linspace(0.0, 3.0, K))[:, None] * np.ones(problem.n_controls)
    return x, u


def fake_result(tau, controller, spread, diverged=0):
    """A ControllerResult built from synthetic runs of the arm (what compare_delays returns)."""
    problem = arm2(delay=tau, noise=True)
    x, u = nominal(problem)
    runs = synthetic_runs(problem, x, u, spread, seed=int(1000 * tau) + len(controller))
    cost = np.asarray(runs.cost).copy()
    cost[:diverged] = np.inf
    runs = runs._replace(cost=cost)
    errors = endpoint_error(problem, runs.x[:, -1])
    return ControllerResult(
        model="arm2", delay=tau, delay_steps=problem.delay_steps, noise=True, controller=controller, converged=True,
        status="CONVERGED_COST", message="", iterations=5, solve_time=0.01, first_solve_time=1.0,
        nominal_cost=1.0, predicted_cost=1.0 + spread, cost=sample_stats(cost),
        endpoint_error=sample_stats(errors, ~np.isfinite(cost)),
        divergence_bound=np.inf, endpoint_label="hand position error", endpoint_unit="m", summary=summarize(cost, runs.x[:, -1]),
        n_trials=N_TRIALS, seed=0, substeps=1, problem=problem, solution=SimpleNamespace(x=x), runs=runs)


@pytest.fixture(scope="module")
def results():
    return [fake_result(0.05, "aware", 0.02), fake_result(0.05, "ignorant", 0.2, diverged=3),
            fake_result(0.1, "aware", 0.03), fake_result(0.1, "ignorant", 0.3)]


def check_png(fig, path):
    fig.savefig(path, dpi=60)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(path)
    width, height = fig.get_size_inches() * 60
    assert image.shape[:2] == (round(height), round(width))


@pytest.mark.parametrize("n_show", [0, 3])
def test_trajectories_have_one_axis_per_state_and_command(tmp_path, n_show):
    problem = arm2(delay=0.05, noise=True)
    x, u = nominal(problem)
    runs = synthetic_runs(problem, x, u, 0.05, seed=0)
    policy = di.Policy(x, u, np.zeros_like(u), np.zeros((problem.horizon, 2, 4)), np.zeros((problem.horizon, 5, 2, 2)))
    fig = plot.plot_trajectories(problem, policy, runs if n_show else None, n_trials=n_show)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 4 + 2
    for ax in fig.axes:
        assert len(ax.get_lines()) == n_show + 1
        assert ax.get_xlabel().startswith("time") and ax.get_ylabel()
    assert fig.axes[0].get_ylabel() == "shoulder angle q1 [rad]"
    assert fig.axes[4].get_ylabel() == "shoulder torque u1 [N m]"
    np.testing.assert_allclose(fig.axes[1].get_lines()[-1].get_ydata(), x[:, 1])       # the nominal, on top
    assert "0.05 s" in fig._suptitle.get_text()
    check_png(fig, tmp_path / "trajectories.png")


def test_own_plant_labels_come_from_its_metadata():
    """A user's plant names its states and commands with ModelMetadata (no task space needed);
    labels of the wrong count are refused when the problem is built."""
    meta = di.models.ModelMetadata(state_labels=("cart x [m]", "angle [rad]", "cart speed [m/s]", "rate [rad/s]"),
                                   control_labels=("force fx [N]", "force fy [N]"))
    problem = point_mass(delay=0.03).replace(name="custom", metadata=meta)
    x, u = nominal(problem)
    fig = plot.plot_trajectories(problem, SimpleNamespace(policy=SimpleNamespace(x_nominal=x, u_nominal=u)))
    assert [ax.get_ylabel() for ax in fig.axes] == list(meta.state_labels + meta.control_labels)
    short = dataclasses.replace(meta, control_labels=("force [N]",))
    with pytest.raises(ValueError, match=r"metadata.control_labels must have one label per command \(d = 2\); got 1"):
        point_mass().replace(metadata=short)


def test_trajectories_of_a_generic_model_use_indexed_labels():
    problem = point_mass(delay=0.03).replace(name="custom", metadata=None)
    x, u = nominal(problem)
    sol = SimpleNamespace(policy=SimpleNamespace(x_nominal=x, u_nominal=u))
    fig = plot.plot_trajectories(problem, sol)
    assert [ax.get_ylabel() for ax in fig.axes] == ["x[0]", "x[1]", "x[2]", "x[3]", "u[0]", "u[1]"]


def test_hand_paths_panel_per_delay_with_paths_endpoints_and_ellipses(tmp_path, results):
    fig = plot.plot_hand_paths(results, n_paths=7)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 2 * 2                                  # two rows, one column per delay
    top, bottom = fig.axes[0], fig.axes[2]                         # first delay: paths, endpoints
    assert len(top.get_lines()) == 2 * (7 + 1)                     # per controller: 7 trials + nominal
    assert top.get_xlabel() == "hand x [m]" and "50 ms" in top.get_title()
    ellipses = [p for p in bottom.patches if isinstance(p, Ellipse)]
    assert len(ellipses) == 2
    # the ellipse of the tighter (aware) controller is the smaller one
    sizes = sorted(e.width * e.height for e in ellipses)
    aware_ellipse = [e for e in ellipses if e.get_label().startswith("delay-aware")][0]
    assert aware_ellipse.width * aware_ellipse.height == sizes[0]
    labels = [t.get_text() for t in bottom.get_legend().get_texts()]
    assert any(s.startswith("delay-aware endpoints") for s in labels) and "target" in labels
    check_png(fig, tmp_path / "hand_paths.png")


def test_hand_paths_need_an_arm(results):
    other = dataclasses.replace(results[0], model="point_mass", problem=point_mass())
    with pytest.raises(ValueError, match="plot_hand_paths needs an arm model"):
        plot.plot_hand_paths([other])


def test_delay_study_has_cost_and_endpoint_axes_with_error_bars(tmp_path, results):
    fig = plot.plot_delay_study(results)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 2
    ax_cost, ax_err = fig.axes
    assert ax_cost.get_yscale() == "log" and ax_cost.get_xlabel() == "input delay [ms]"
    assert ax_err.get_ylabel() == "hand position error [mm]"
    labels = [t.get_text() for t in ax_cost.get_legend().get_texts()]
    assert "delay-aware: Monte Carlo mean, 95% CI" in labels
    assert "delay-ignorant: Monte Carlo mean, 95% CI" in labels    # over the 37 trials that did not diverge
    assert "delay-ignorant: its own predicted E[J]" in labels
    # one definition of a diverged trial: both panels count the same 3 of 40 at 50 ms
    for ax in (ax_cost, ax_err):
        assert [t.get_text() for t in ax.texts] == ["3/40 diverged"]
    ignorant_bar = [c for c in ax_cost.containers if c.get_label() == "delay-ignorant: Monte Carlo mean, 95% CI"][0]
    np.testing.assert_allclose(ignorant_bar.lines[0].get_ydata(), [results[1].cost.mean, results[3].cost.mean])
    assert math.isfinite(results[1].cost.mean) and results[1].cost.n_diverged == 3
    # the aware means are drawn where they are, in the error-bar containers
    aware_bar = [c for c in ax_cost.containers if c.get_label() == "delay-aware: Monte Carlo mean, 95% CI"][0]
    np.testing.assert_allclose(aware_bar.lines[0].get_ydata(), [results[0].cost.mean, results[2].cost.mean])
    check_png(fig, tmp_path / "cost_vs_delay.png")


def test_convergence_has_one_line_per_solution_on_a_log_scale(tmp_path):
    def solution(costs, converged=True):
        n = len(costs)
        nan = np.full(n + 3, np.nan)
        trace = di.Trace(cost=np.r_[costs, nan[n:]], merit=np.r_[costs, nan[n:]],
                         expected_reduction=nan, step_size=np.r_[np.nan, np.ones(n - 1), nan[n:]], reg=nan,
                         grad_norm=nan)
        return di.Solution(x=None, u=None, cost=costs[-1], expected_cost=costs[-1],
                           status=np.int32(1 if converged else 2), iterations=np.int32(n - 1), policy=None,
                           trace=trace)

    fig = plot.plot_convergence({"a": solution([100.0, 10.0, 1.0]), "b": solution([50.0, 5.0, 4.0, 3.9], False)})
    assert isinstance(fig, Figure) and len(fig.axes) == 1
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and len(ax.get_lines()) == 2
    np.testing.assert_allclose(ax.get_lines()[1].get_ydata(), [50.0, 5.0, 4.0, 3.9])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["a: cost (converged)", "b: cost (not converged)"]
    single = plot.plot_convergence(solution([3.0, 2.0]))
    assert len(single.axes[0].get_lines()) == 1
    check_png(fig, tmp_path / "convergence.png")


def test_importing_the_package_and_plot_does_not_import_matplotlib():
    code = "import sys, delayed_ilqr, delayed_ilqr.plot, delayed_ilqr.cli; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
