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
from delayed_ilqr.experiments.center_out import DelayResult, TargetResult
from delayed_ilqr.experiments.delay_study import ControllerResult
from delayed_ilqr.models import arm2_muscle6
from delayed_ilqr.models.metadata import task_position
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
    problem = arm2(delay=tau, noise="benchmark")
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
    problem = arm2(delay=0.05, noise="benchmark")
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
    assert "50 ms" in fig._suptitle.get_text()                 # delays in ms, as in every figure
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
    assert len(fig.axes) == 3 * 2                                  # three rows, one column per delay
    top, middle, bottom = fig.axes[0], fig.axes[2], fig.axes[4]    # first delay: paths, speed, endpoints
    assert len(top.get_lines()) == 2 * (7 + 1)                     # per controller: 7 trials + nominal
    assert top.get_xlabel() == "hand x [m]" and "50 ms" in top.get_title()
    # hand speed in cm/s: the nominal's hand displacement per step over dt, 1 m/s = 100 cm/s
    assert len(middle.get_lines()) == 2 * (7 + 1) and middle.get_ylabel() == "hand speed [cm/s]"
    problem = results[0].problem
    q = np.asarray(results[0].solution.x)[:, :2]
    l1, l2 = 0.30, 0.33                                            # arm2's segment lengths (docs/models.md)
    hand = np.stack([l1 * np.cos(q[:, 0]) + l2 * np.cos(q[:, 0] + q[:, 1]),
                     l1 * np.sin(q[:, 0]) + l2 * np.sin(q[:, 0] + q[:, 1])], axis=1)
    speed = 100.0 * np.linalg.norm(np.diff(hand, axis=0), axis=1) / problem.dt
    np.testing.assert_allclose(middle.get_lines()[7].get_ydata(), speed, rtol=1e-12)
    assert fig.axes[3].get_ylim() == middle.get_ylim()            # one speed scale across delays
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
    assert len(fig.axes) == 3
    ax_cost, ax_err, ax_spread = fig.axes
    assert ax_cost.get_yscale() == "log" and ax_cost.get_xlabel() == "input delay [ms]"
    assert ax_err.get_ylabel() == "hand position error [mm]"
    labels = [t.get_text() for t in ax_cost.get_legend().get_texts()]
    assert "delay-aware: Monte Carlo mean, 95% CI" in labels
    assert "delay-ignorant: Monte Carlo mean, 95% CI" in labels    # over the 37 trials that did not diverge
    assert "delay-ignorant: its own predicted E[J]" in labels
    # one definition of a diverged trial: both panels count the same 3 of 40 at 50 ms
    for ax in (ax_cost, ax_err):
        assert [t.get_text() for t in ax.texts] == ["3/40 diverged"]
    assert ax_err.get_title() == "hand position error"
    # the spread: 1-sigma major axis (mm) of the final hand positions of the same 37 trials
    r = results[1]
    ends = task_position(r.problem, r.runs.x[3:, -1])
    major = 1e3 * np.sqrt(np.linalg.eigvalsh(np.cov(ends, rowvar=False))[-1])
    ignorant_spread = [line for line in ax_spread.get_lines() if line.get_label() == "delay-ignorant: Monte Carlo"][0]
    np.testing.assert_allclose(ignorant_spread.get_ydata()[0], major, rtol=1e-12)
    assert ax_spread.get_ylabel() == "1-sigma major axis [mm]"
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


def fake_reaches(tau, design, spread_mm, n_targets=3, n_trials=30):
    """A center-out DelayResult of the muscle arm from synthetic states: straight-line nominals in
    joint space and endpoints scattered by ``spread_mm`` around each target (no solve)."""
    rng = np.random.default_rng(int(1e3 * tau) + len(design))
    plants, targets, xs, runs = [], [], [], []
    for j in range(n_targets):
        angle = 2 * np.pi * j / n_targets
        plant = arm2_muscle6(delay=tau, target=(-0.02 + 0.1 * np.cos(angle), 0.45 + 0.1 * np.sin(angle)))
        K = plant.horizon
        x = np.asarray(plant.x0)[None] + np.linspace(0.0, 1.0, K + 1)[:, None] * 0.1 * rng.standard_normal(plant.n_states)
        target = np.asarray(plant.cost.params["target"])
        ends = target + 1e-3 * spread_mm * rng.standard_normal((n_trials, 2)) * np.array([2.0, 1.0])
        plants.append(plant)
        xs.append(x)
        runs.append(SimpleNamespace(x=np.repeat(x[None], n_trials, axis=0)))
        targets.append(TargetResult(target=target, status="CONVERGED_COST", iterations=10, cost=1.0,
                                    predicted_cost=1.0, hand_error=1e-4, hand_speed=1e-3, endpoints=ends,
                                    mc_error=np.linalg.norm(ends - target, axis=1), mc_cost=1.0 + rng.random(n_trials),
                                    diverged=np.zeros(n_trials, bool)))
    solutions = SimpleNamespace(x=np.stack(xs), u=rng.random((n_targets, plants[0].horizon, 6)))
    return DelayResult(delay=tau, delay_steps=round(tau / 0.01), dt=0.01, design=design, solve_time=0.1, first_call=1.0,
                       targets=targets, solutions=solutions, runs=runs, plants=plants)


@pytest.fixture(scope="module")
def reaches():
    return [fake_reaches(tau, design, spread) for tau, spread in ((0.0, 0.5), (0.05, 3.0))
            for design, spread in (("noise-aware", spread), ("deterministic", 2 * spread))]


def test_center_out_figures_have_speed_profiles_endpoints_in_mm_and_delay_trends(tmp_path, reaches):
    figures = plot.center_out_figures(reaches)
    assert set(figures) == {"center_out_hand_paths.png", "center_out_speed.png", "center_out_endpoints.png",
                            "center_out_vs_delay.png", "center_out_excitations_noise-aware_0ms.png",
                            "center_out_excitations_deterministic_0ms.png", "center_out_excitations_noise-aware_50ms.png",
                            "center_out_excitations_deterministic_50ms.png"}
    # every figure has a caption naming the human finding it is compared with
    for name in figures:
        caption = [c for key, c in plot.CAPTIONS.items() if name == key or name.startswith(key + "_")]
        assert len(caption) == 1 and "Compared with:" in caption[0], name
    # speed: one line per target, cm/s from the hand displacement per step
    speed = figures["center_out_speed.png"].axes
    assert len(speed) == 4 and speed[0].get_ylabel() == "hand speed [cm/s]"
    r = reaches[0]
    hand = task_position(r.plants[1], r.solutions.x[1])
    np.testing.assert_allclose(speed[0].get_lines()[1].get_ydata(),
                               100 * np.linalg.norm(np.diff(hand, axis=0), axis=1) / r.dt, rtol=1e-12)
    # endpoints: in mm relative to each target, the 2-sigma ellipse of each target's trials
    ends = figures["center_out_endpoints.png"].axes[0]
    assert ends.get_xlabel() == "endpoint x - target x [mm]"
    ellipses = [p for p in ends.patches if isinstance(p, Ellipse)]
    assert len(ellipses) == 3
    rel = 1e3 * (r.targets[0].endpoints - r.targets[0].target)
    major = 2 * 2 * np.sqrt(np.linalg.eigvalsh(np.cov(rel, rowvar=False))[-1])
    np.testing.assert_allclose(ellipses[0].width, major, rtol=1e-12)
    # against the delay: the pooled Monte Carlo mean cost and the mean spread over targets (mm)
    ax_cost, ax_spread = figures["center_out_vs_delay.png"].axes
    aware = [c for c in ax_spread.containers if c.get_label().startswith("noise-aware")][0]
    expected = [np.mean([1e3 * t.spread for t in reaches[i].targets]) for i in (0, 2)]
    np.testing.assert_allclose(aware.lines[0].get_ydata(), expected, rtol=1e-12)
    cost = [c for c in ax_cost.containers if c.get_label().startswith("deterministic")][0]
    np.testing.assert_allclose(cost.lines[0].get_ydata(),
                               [np.mean(np.concatenate([t.mc_cost for t in reaches[i].targets])) for i in (1, 3)])
    for name in ("center_out_speed.png", "center_out_endpoints.png", "center_out_vs_delay.png"):
        check_png(figures[name], tmp_path / name)


def test_center_out_report_captions_every_figure(tmp_path, reaches):
    from delayed_ilqr.experiments import report
    figures = report.save_figures(plot.center_out_figures(reaches[:2]), tmp_path)
    settings = dict(targets=3, radius=0.1, trials=30, sigma_u=0.01, seed=0, designs=["noise-aware", "deterministic"],
                    elapsed_seconds=1.0)
    report.write_center_out_report(tmp_path, reaches[:2], settings, "table", figures)
    text = (tmp_path / "center_out.md").read_text()
    for name in figures:
        after = text.split(f"![{name}]({name})", 1)[1].lstrip("\n").split("\n", 1)[0]
        assert after and not after.startswith("!["), name
    assert "Flash & Hogan 1985" in text and "Gordon, Ghilardi & Ghez 1994" in text



# --------------------------------------------------------------------------------------------
# The checklist over every figure the plot module makes
# --------------------------------------------------------------------------------------------
def _drawn(artist) -> bool:
    """Whether a labelled artist puts something on the canvas (a line with points, a collection
    with offsets or paths, a patch, a container with such parts)."""
    from matplotlib.collections import Collection, PathCollection
    from matplotlib.container import Container
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    if isinstance(artist, Container):
        return any(_drawn(a) for a in artist.get_children() if a is not None)
    if not artist.get_visible():
        return False
    if isinstance(artist, Line2D):
        return len(artist.get_xdata()) > 0 and artist.get_linestyle() not in ("None", " ", "") \
            or len(artist.get_xdata()) > 0 and artist.get_marker() not in ("None", " ", "", None)
    if isinstance(artist, PathCollection):                     # a scatter: its points
        return len(artist.get_offsets()) > 0
    if isinstance(artist, Collection):
        return len(artist.get_paths()) > 0
    return isinstance(artist, Patch)


def _labelled_artists(fig) -> dict:
    found = {}
    for ax in fig.axes:
        for artist in list(ax.get_children()) + list(ax.containers):
            label = artist.get_label() if hasattr(artist, "get_label") else None
            if isinstance(label, str) and label and not label.startswith("_"):
                found.setdefault(label, []).append(artist)
    return found


def figure_problems(fig) -> list[str]:
    """What a figure breaks of the checklist: a title present and inside the canvas (axes titles
    too), every axis labelled with a unit in brackets (an axis sharing a labelled sibling may go
    without), speeds in cm/s and delays in ms, and every legend entry backed by a drawn artist."""
    import re
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    problems = []
    axes = [ax for ax in fig.axes if ax.get_visible()]
    suptitle = fig._suptitle.get_text() if fig._suptitle is not None else ""
    if not suptitle and not (len(axes) == 1 and axes[0].get_title()):
        problems.append("no title")
    titles = ([fig._suptitle] if suptitle else []) + [ax.title for ax in axes if ax.get_title()]
    box = fig.bbox
    for t in titles:
        e = t.get_window_extent(renderer)
        if e.x0 < box.x0 - 0.5 or e.x1 > box.x1 + 0.5 or e.y0 < box.y0 - 0.5 or e.y1 > box.y1 + 0.5:
            problems.append(f"title outside the canvas: {t.get_text()!r}")
        if re.search(r"\b\d+(\.\d+)? s\b", t.get_text()):
            problems.append(f"a time in seconds in a title (delays in ms): {t.get_text()!r}")
    for ax in axes:
        for which in "xy":
            label = ax.get_xlabel() if which == "x" else ax.get_ylabel()
            shared = (ax.get_shared_x_axes() if which == "x" else ax.get_shared_y_axes()).get_siblings(ax)
            if not label:
                if not any(o is not ax and (o.get_xlabel() if which == "x" else o.get_ylabel()) for o in shared):
                    problems.append(f"unlabelled {which} axis in {ax.get_title()!r}")
                continue
            if not re.search(r"\[[^\]]+\]$", label):
                problems.append(f"no unit in brackets: {label!r}")
            if "speed" in label and not label.endswith("[cm/s]"):
                problems.append(f"a speed not in cm/s: {label!r}")
            if "delay" in label and not label.endswith("[ms]"):
                problems.append(f"a delay not in ms: {label!r}")
    artists = _labelled_artists(fig)
    legends = [ax.get_legend() for ax in axes if ax.get_legend() is not None] + list(fig.legends)
    for legend in [ax.get_legend() for ax in axes if ax.get_legend() is not None] + list(fig.legends):
        e = legend.get_window_extent(renderer)
        if e.x0 < box.x0 - 0.5 or e.x1 > box.x1 + 0.5 or e.y0 < box.y0 - 0.5 or e.y1 > box.y1 + 0.5:
            problems.append("a legend outside the canvas")
    if suptitle:
        for legend in fig.legends:
            if fig._suptitle.get_window_extent(renderer).overlaps(legend.get_window_extent(renderer)):
                problems.append("the title runs under a legend")
    for legend in legends:
        for text in legend.get_texts():
            if not any(_drawn(a) for a in artists.get(text.get_text(), [])):
                problems.append(f"a legend entry for nothing drawn: {text.get_text()!r}")
    return problems


def _without_titles(fig) -> bytes:
    """The figure rendered with every title removed (to find figures that differ only there)."""
    import hashlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    if fig._suptitle is not None:
        fig._suptitle.set_text("")
    for ax in fig.axes:
        ax.set_title("")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return hashlib.sha256(np.asarray(canvas.buffer_rgba()).tobytes()).digest()


def fake_perturbation(sensory_delays=(0.0, 0.05)):
    """PerturbationResult-like records of the arm from synthetic runs (no solve)."""
    out = []
    for i, ls in enumerate(sensory_delays):
        problem = arm2(delay=0.05, noise=True, sensory_delay=ls)
        x, u = nominal(problem)
        base = synthetic_runs(problem, x, u, 0.01, seed=i)
        kicked = base._replace(x=np.asarray(base.x) + 0.02 * np.linspace(0, 1, problem.horizon + 1)[None, :, None],
                               u=np.asarray(base.u) + 0.5)
        out.append(SimpleNamespace(problem=problem, sensory_delay=ls, pulse_step=15, latency_steps=16 + 5 * i,
                                   base=base, perturbed=kicked))
    return out


def fake_sweep():
    """A sweep Dataset as delayed_ilqr.sweep writes it (the variables plot_sweep reads), synthetic."""
    import xarray as xr
    rng = np.random.default_rng(0)
    shape = (3, 2, 2)
    cost = 1.0 + rng.random(shape)
    dims = ("delay", "sigma_u", "seed")
    return xr.Dataset(
        {"status": (dims[:2], np.ones(shape[:2], np.int32)),
         "mc_cost_mean": (dims, cost, dict(long_name="Monte Carlo mean cost", units="1")),
         "mc_cost_ci_low": (dims, 0.9 * cost, dict(long_name="Monte Carlo mean cost, 95 % CI low", units="1")),
         "mc_cost_ci_high": (dims, 1.1 * cost, dict(long_name="Monte Carlo mean cost, 95 % CI high", units="1")),
         "mc_endpoint_error_median": (dims, 1e-3 * cost, dict(long_name="median hand position error", units="m"))},
        coords={"delay": ("delay", [0.0, 0.05, 0.1], dict(units="s")),
                "sigma_u": ("sigma_u", [0.01, 0.02], dict(units="s^1/2")), "seed": ("seed", [0, 1])},
        attrs=dict(model="arm2", trials=20))


def fake_gallery():
    """The gallery's results (kick, target jump, Fitts, minimal intervention, delay growth) built
    from synthetic runs of the reach problems (no solve): {name: Figure} of `plot.gallery`."""
    from delayed_ilqr.experiments import delay_growth, fitts, kick, minimal_intervention, reach_tasks, target_jump
    from delayed_ilqr.plot import gallery
    muscle = reach_tasks.reach("arm2_muscle6", delay=0.03, sensory_delay=0.05)
    x, _ = nominal(arm2(delay=0.03))
    mx = np.concatenate([x, np.full((x.shape[0], 6), 0.05)], axis=1)
    mu = np.full((muscle.horizon, 6), 0.05)
    base = synthetic_runs(muscle, mx, mu, 0.01, seed=0)
    kicked = base._replace(x=np.asarray(base.x) + 0.02 * np.linspace(0, 1, muscle.horizon + 1)[None, :, None],
                           u=np.asarray(base.u) + np.where(np.arange(muscle.horizon) >= 30, 0.2, 0.0)[None, :, None])
    trials = lambda runs: SimpleNamespace(runs=runs, errors=np.abs(np.asarray(runs.x)[:, -1, 0]))  # noqa: E731
    errors = sample_stats(np.abs(np.asarray(base.x)[:, -1, 0]))
    analysis = kick.KickAnalysis(0.08, 0.09, 0.08, 0.02, errors, errors, 1.0)
    kick_result = kick.KickResult(muscle, None, None, 24, trials(base), trials(kicked), analysis, 0.15)
    torque = reach_tasks.with_target_state(reach_tasks.reach("arm2", delay=0.03, sensory_delay=0.05))
    tx = np.concatenate([x, np.tile(np.asarray(torque.x0)[-2:], (x.shape[0], 1))], axis=1)
    jx = np.asarray(synthetic_runs(torque, tx, np.zeros((torque.horizon, 2)), 0.01, seed=1).x)
    jumps = [target_jump.JumpAnalysis(t, 0.08, 0.1, 0.08, errors, 0.9, 0.1) for t in (0.1, 0.3)]
    jump_result = target_jump.JumpResult(torque, None, np.array([0.0, 0.02]), jx, [jx + 0.001, jx + 0.002], jumps)
    ds, ws, ts = np.array([0.04, 0.08, 0.16]), np.array([0.01, 0.02, 0.04]), np.array([0.2, 0.3, 0.4])
    index = np.log2(2 * ds[:, None] / ws[None, :])
    fitts_results = [fitts.FittsResult(d, 0.05, ds, ws, ts, np.zeros((3, 3)), np.ones((3, 3)), None,
                                       a + 0.15 * index, index, responses_fit(index, a + 0.15 * index))
                     for d, a in ((0.03, 0.1), (0.09, 0.2))]
    rng = np.random.default_rng(3)
    scatters = [minimal_intervention.analyse(name, np.asarray(muscle.cost.params["target"])
                                             + 1e-3 * rng.standard_normal((50, 2)) * scale, [1.0, 0.0],
                                             problem=muscle)
                for name, scale in (("point", [1.0, 1.0]), ("bar", [2.0, 1.0]))]
    point = lambda d, s, c: delay_growth.DelayPoint(d, s, d + (s or 0), sample_stats(c + rng.random(20)),  # noqa: E731
                                                    1e-3 * c, 2e-3 * c, c, None if s else 1e-3 * c, None if s else 2e-3 * c, ())
    growth = delay_growth.DelayGrowth([point(d, None, 1 + 10 * d) for d in (0.0, 0.04, 0.08)],
                                      [point(0.03, s, 1 + 5 * s) for s in (0.0, 0.04, 0.08)], muscle)
    return {"kick.png": gallery.plot_kick(kick_result), "target_jump.png": gallery.plot_target_jump(jump_result),
            "fitts.png": gallery.plot_fitts(fitts_results),
            "minimal_intervention.png": gallery.plot_minimal_intervention(scatters),
            "delay_growth.png": gallery.plot_delay_growth(growth)}


def responses_fit(index, mt):
    from delayed_ilqr.experiments.responses import fitts_fit
    return fitts_fit(index, mt)


def every_figure(results, reaches):
    """Every figure the plot module makes, by a name, from synthetic inputs: {group: {name: Figure}}
    (a group is what one call or one command writes together)."""
    from delayed_ilqr.models import arm2_muscle6
    problem = arm2(delay=0.05, noise=True)
    x, u = nominal(problem)
    policy = di.Policy(x, u, np.zeros_like(u), np.zeros((problem.horizon, 2, 4)), np.zeros((problem.horizon, 5, 2, 2)))
    muscle = arm2_muscle6(delay=0.05)
    mx = np.tile(np.asarray(muscle.x0), (muscle.horizon + 1, 1))
    mu = np.full((muscle.horizon, 6), 0.05)
    muscle_policy = di.Policy(mx, mu, np.zeros_like(mu), np.zeros((muscle.horizon, 6, 10)),
                              np.zeros((muscle.horizon, 5, 6, 6)))

    def solution(costs, steps):
        n = len(costs)
        trace = di.Trace(cost=np.asarray(costs), merit=np.asarray(costs) * 1.1, expected_reduction=np.zeros(n),
                         step_size=np.asarray(steps), reg=np.zeros(n), grad_norm=np.zeros(n))
        return di.Solution(x=None, u=None, cost=costs[-1], expected_cost=costs[-1], status=np.int32(1),
                           iterations=np.int32(n - 1), policy=None, trace=trace)

    statistical = [dataclasses.replace(r, design="statistical") for r in reaches if r.design == "noise-aware"]
    return {
        "trajectories": {"arm2": plot.plot_trajectories(problem, policy, synthetic_runs(problem, x, u, 0.05, 0)),
                         "muscle": plot.plot_trajectories(muscle, muscle_policy)},
        "convergence, no rejected step": {"c": plot.plot_convergence({"a": solution([3.0, 2.0, 1.0], [np.nan, 1, 1])})},
        "convergence, rejected steps": {"c": plot.plot_convergence({"a": solution([3.0, 2.0, 1.9], [np.nan, 1, 0])})},
        # delay_study_figures adds convergence.png of the solutions, drawn above from synthetic traces
        "delay study": {"cost_vs_delay.png": plot.plot_delay_study(results),
                        "hand_paths.png": plot.plot_hand_paths(results)},
        "center-out": plot.center_out_figures(reaches + statistical),
        "center-out, one delay and design (narrow figures)": plot.center_out_figures(reaches[:1]),
        "perturbation": plot.perturbation_figures(fake_perturbation()),
        "sweep": {"sweep.png": plot.plot_sweep(fake_sweep())},
        "gallery": fake_gallery(),
    }


def test_every_figure_passes_the_checklist(results, reaches):
    """Titles inside the canvas, units on every axis (speeds in cm/s, delays in ms), legends that
    name only what is drawn, and no figure that repeats another of its group but for the titles
    (the statistical design's excitations are the noise-aware nominal's: drawn once)."""
    groups = every_figure(results, reaches)
    problems = {f"{group}/{name}": figure_problems(fig) for group, figures in groups.items()
                for name, fig in figures.items()}
    assert {k: v for k, v in problems.items() if v} == {}
    assert "center_out_excitations_statistical_0ms.png" not in groups["center-out"]
    for group, figures in groups.items():
        prints = [_without_titles(fig) for fig in figures.values()]
        assert len(set(prints)) == len(prints), group


def test_the_checklist_catches_what_it_is_for():
    """Each rule fails on a figure built to break it (so that the checklist can fail)."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(3, 2))
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], label="drawn")
    ax.scatter([], [], label="rejected steps")
    ax.legend()
    ax.set_xlabel("input delay [s]")
    ax.set_ylabel("hand speed [m/s]")
    fig.suptitle("a title far too long for this narrow figure, which runs off both sides of the canvas")
    found = " | ".join(figure_problems(fig))
    for rule in ("title outside the canvas", "a delay not in ms", "a speed not in cm/s",
                 "a legend entry for nothing drawn: 'rejected steps'"):
        assert rule in found, rule
    wide = Figure(figsize=(2, 2))
    wide.subplots().plot([0, 1], [0, 1], label="a line")
    wide.legend(loc="outside lower center", ncol=1, labels=["a legend entry far wider than the figure itself"])
    assert "a legend outside the canvas" in " | ".join(figure_problems(wide))
    bare = Figure()
    bare.subplots(1, 2)[0].set_ylabel("cost")
    found = " | ".join(figure_problems(bare))
    assert "no title" in found and "no unit in brackets: 'cost'" in found and "unlabelled x axis" in found
