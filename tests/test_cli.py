"""The ``delayed-ilqr`` command line, run in-process with click's CliRunner.

Settings reuse the shapes the other tests compile (noisy point mass at 30 ms, noisy arm at 50 and
100 ms with 300 trials), so most calls hit JAX's compilation cache.
"""
import json

import numpy as np
import pytest
from click.testing import CliRunner

import delayed_ilqr as di
from delayed_ilqr import cli
from delayed_ilqr.experiments import engine
from delayed_ilqr.experiments.designs import design
from delayed_ilqr.experiments.records import problem_record
from delayed_ilqr.models import REGISTRY, arm2, point_mass


DESIGN = design(point_mass(), "aware")[1]   # the options the CLI designs controllers with

def run(*args):
    return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)


def test_models_lists_the_registry():
    result = run("models")
    assert result.exit_code == 0
    lines = result.output.strip().splitlines()
    assert len(lines) == len(REGISTRY)
    for name, info in REGISTRY.items():
        assert any(line.startswith(name) and info.description in line for line in lines)


def test_solve_writes_json_npz_and_figures_consistent_with_the_api(tmp_path):
    result = run("solve", "point_mass", "--delay", "0.03", "--noise", "--out", tmp_path)
    assert result.exit_code == 0, result.output
    assert "CONVERGED" in result.output and "expected cost (LQG)" in result.output
    sol = di.solve(point_mass(delay=0.03, noise=True))   # `solve` uses the default Options
    data = json.loads((tmp_path / "solution.json").read_text())
    assert data["model"] == "point_mass" and data["delay_steps"] == 3 and data["noise"] is True
    assert data["converged"] is True and data["iterations"] == int(sol.iterations)
    np.testing.assert_allclose(data["cost"], float(sol.cost), rtol=1e-12)
    np.testing.assert_allclose(data["expected_cost"], float(sol.expected_cost), rtol=1e-12)
    target = np.asarray(point_mass().cost.x_target)
    np.testing.assert_allclose(data["endpoint_error"], np.linalg.norm(np.asarray(sol.x[-1, :2]) - target[:2]),
                               rtol=1e-12)
    saved = di.load(tmp_path / "solution.npz")                # the saved-solution format: it loads back
    assert saved.x.shape == (61, 4) and saved.policy.delay_feedback.shape == (60, 3, 2, 2)
    assert saved.status is di.Status(int(sol.status)) and int(saved.iterations) == int(sol.iterations)
    np.testing.assert_allclose(saved.u, sol.u, rtol=1e-12)
    np.testing.assert_allclose(saved.trace.cost, sol.trace.cost, rtol=1e-12)
    meta = di.load_metadata(tmp_path / "solution.npz")
    assert (meta["dt"], meta["delay_steps"], meta["info"]["model"]) == (0.01, 3, "point_mass")
    problem = point_mass(delay=0.03, noise=True)
    np.testing.assert_allclose(di.simulate(problem, saved.policy, 8, seed=2).cost,
                               di.simulate(problem, sol.policy, 8, seed=2).cost, rtol=1e-10)
    for png in ("trajectories.png", "convergence.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_solve_that_does_not_converge_exits_with_1(monkeypatch):
    real = engine.timed_solve

    def stopped_early(*args, **kwargs):            # the solution as if the iteration limit had been hit
        sol, solve_time, first = real(*args, **kwargs)
        return sol._replace(status=np.int32(di.Status.MAX_ITERATIONS)), solve_time, first

    monkeypatch.setattr(engine, "timed_solve", stopped_early)
    result = CliRunner().invoke(cli.main, ["solve", "point_mass", "--delay", "0.03", "--noise"])
    assert result.exit_code == 1
    assert "did not converge" in result.output and "MAX_ITERATIONS" in result.output


def test_simulate_summary_matches_a_direct_monte_carlo(tmp_path):
    result = run("simulate", "point_mass", "--delay", "0.03", "--trials", 16, "--seed", 3, "--noise",
                 "--out", tmp_path)
    assert result.exit_code == 0, result.output
    assert "Monte Carlo mean J" in result.output
    problem = point_mass(delay=0.03, noise=True)
    runs = di.simulate(problem, di.solve(problem, options=DESIGN).policy, 16, seed=3)
    summary = runs.summary()
    data = json.loads((tmp_path / "simulate.json").read_text())
    assert data["settings"] == dict(model="point_mass", noise=True, trials=16, seed=3, substeps=1, delay=0.03,
                                    controller="aware", problem=json.loads(json.dumps(problem_record(problem))))
    res = data["result"]
    np.testing.assert_allclose(res["cost"]["mean"], summary.mean_cost, rtol=1e-12)
    np.testing.assert_allclose(res["cost"]["ci95"], summary.ci95, rtol=1e-12)
    np.testing.assert_allclose(res["summary"]["final_state_cov"], summary.final_state_cov, rtol=1e-10)
    with np.load(tmp_path / "runs.npz") as npz:
        assert npz["x"].shape == (16, 61, 4) and npz["u"].shape == (16, 60, 2) and npz["cost"].shape == (16,)
        np.testing.assert_allclose(npz["cost"], np.asarray(runs.cost), rtol=1e-12)
        assert npz["delay_feedback"].shape == (60, 3, 2, 2)
    saved = di.load(tmp_path / "solution.npz")                # the policy that ran, loadable
    rerun = di.simulate(problem, saved.policy, 16, seed=3)
    np.testing.assert_allclose(rerun.cost, runs.cost, rtol=1e-12)
    assert (tmp_path / "trajectories.png").exists() and not (tmp_path / "hand_paths.png").exists()


def test_compare_on_the_arm_writes_table_json_npz_and_figures(tmp_path):
    result = run("compare", "arm2", "--delays", "0.05,0.1", "--trials", 300, "--seed", 0, "--out", tmp_path)
    assert result.exit_code in (0, 1), result.output          # 1: a solve did not converge (said so)
    if result.exit_code == 1:
        assert "did not converge" in result.output
    for word in ("50 ms", "100 ms", "controller", "aware", "ignorant", "MC median J", "hand position error [mm]"):
        assert word in result.output
    data = json.loads((tmp_path / "compare.json").read_text())
    assert data["settings"]["delays"] == [0.05, 0.1] and data["settings"]["trials"] == 300
    rows = data["results"]
    assert [(r["delay"], r["controller"]) for r in rows] == [(0.05, "aware"), (0.05, "ignorant"),
                                                             (0.1, "aware"), (0.1, "ignorant")]
    problem = arm2(delay=0.1, noise=True)                # compare's default noise: the human preset
    sol = di.solve(problem, options=DESIGN)
    summary = di.simulate(problem, sol.policy, 300, seed=0).summary()
    aware = rows[2]
    np.testing.assert_allclose(aware["cost"]["mean"], summary.mean_cost, rtol=1e-12)
    np.testing.assert_allclose(aware["cost"]["median"], summary.median_cost, rtol=1e-12)
    np.testing.assert_allclose(aware["predicted_cost"], float(sol.expected_cost), rtol=1e-12)
    assert rows[3]["cost"]["median"] > 10 * aware["cost"]["median"]
    with np.load(tmp_path / "compare_runs.npz") as npz:
        assert npz["aware_100ms_x"].shape == (300, 51, 4)
        assert npz["ignorant_100ms_delay_feedback"].shape == (50, 0, 2, 2)
        assert npz["aware_100ms_delay_feedback"].shape == (50, 10, 2, 2)
    assert "| delay | controller |" in (tmp_path / "compare.md").read_text()
    for png in ("cost_vs_delay.png", "hand_paths.png", "convergence.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_writes_the_report(tmp_path):
    out = tmp_path / "report"
    result = run("demo", "--out", out, "--trials", 300)
    assert result.exit_code in (0, 1), result.output
    if result.exit_code == 1:
        assert "did not converge" in result.output
    assert result.output.count("aware") >= 3 and result.output.count("ignorant") >= 3
    report = (out / "report.md").read_text()
    assert "| delay | controller |" in report and "| 50 ms | aware |" in report and "![" in report
    data = json.loads((out / "report.json").read_text())
    assert data["settings"]["model"] == "arm2" and data["settings"]["noise"] is True
    noise = data["settings"]["problems"][0]["noise"]            # human-level noise, not P2-noisy's 0.2
    assert (noise["preset"], noise["sigma_u"]) == ("human", 0.01)
    assert [r["delay"] for r in data["results"]] == [0.0, 0.0, 0.05, 0.05, 0.1, 0.1, 0.15, 0.15]
    assert all(r["n_trials"] == 300 for r in data["results"])
    for png in ("cost_vs_delay.png", "hand_paths.png", "convergence.png"):
        assert (out / png).exists()


def test_perturb_writes_the_responses_and_the_first_response_is_one_step_plus_the_sensory_delay(tmp_path):
    result = run("perturb", "point_mass", "--delay", "0.03", "--sensory-delays", "0,0.05", "--pulse-time", "0.2",
                 "--trials", "20", "--out", tmp_path)
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "perturb.json").read_text())
    assert [r["sensory delay [ms]"] for r in data["results"]] == [0.0, 50.0]
    # W_kp enters x_{kp+1}: the first command that can respond is u_{kp+1+l_s}
    assert [r["first response [ms after kick]"] for r in data["results"]] == pytest.approx([10.0, 60.0])
    problem = point_mass(delay=0.03, noise=True, sensory_delay=0.05)
    sol = di.solve(problem)
    np.testing.assert_allclose(data["results"][1]["local prediction E[J] (linearised)"], float(sol.expected_cost), rtol=1e-12)
    with np.load(tmp_path / "perturb_means.npz") as npz:
        kicked, calm = npz["ls50ms_x_kicked_mean"], npz["ls50ms_x_mean"]
        assert kicked.shape == (61, 4)
        np.testing.assert_array_equal(kicked[:21], calm[:21])
        assert np.linalg.norm(kicked[21, 2:] - calm[21, 2:]) == pytest.approx(0.2, rel=1e-12)   # the kick, m/s
    assert (tmp_path / "perturbation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "manifest.json" in result.output


@pytest.mark.parametrize("args, message", [
    (["solve", "no_such_model"], "must be a built-in model (acrobot, arm2, arm2_muscle6, cart_pole, pendulum, "
                                 "planar_quadrotor, point_mass) or package.module:factory; got 'no_such_model'"),
    (["solve", "no_such_module_xyz:f"], "cannot import module 'no_such_module_xyz'"),
    (["solve", "delayed_ilqr.models:REGISTRY"], "'delayed_ilqr.models' has no callable 'REGISTRY'"),
    (["solve", "delayed_ilqr.models:"], "has no callable ''"),
    (["solve", "point_mass", "--param", "sigma"], "must be key=value with key a Python name"),
    (["solve", "point_mass", "--param", "x0=(0, zero)"], "the value of x0 must be a Python literal"),
    (["solve", "point_mass", "--param", "mass=2.0"], "unexpected keyword argument 'mass'"),
    (["solve", "point_mass", "--param", "delay=0.1"], "delay is set by its own option"),
    (["solve", "point_mass", "--param", "horizon=5", "--param", "horizon=6"], "horizon is given twice"),
    (["solve", "point_mass", "--dt", "0.01", "--param", "dt=0.02"], "dt is given both as --dt and as --param"),
    (["solve", "point_mass", "--dt", "0"], "--dt"),
    (["compare", "point_mass", "--dt", "0.02", "--delays", "0,0.03"], "must be a whole number of steps of dt=0.02"),
    (["solve", "arm2", "--delay", "-0.01"], "--delay"),
    (["simulate", "arm2", "--delay", "-0.025", "--trials", "3"], "--delay"),
    (["solve", "point_mass", "--delay", "0.02,0.05"], "takes one delay in seconds for every command channel "
                                                       "(per-channel delays are set in Python"),
    (["mpc", "point_mass", "--true-delay", "0.02,0.05"], "--true-delay"),
    (["simulate", "arm2", "--trials", "0"], "--trials"),
    (["simulate", "arm2", "--trials", "-4"], "--trials"),
    (["simulate", "arm2", "--seed", "-1"], "--seed"),
    (["compare", "arm2", "--delays", "0,0.025"], "--delays"),
    (["compare", "arm2", "--delays", "a,b"], "--delays"),
    (["compare", "arm2", "--trials", "0"], "--trials"),
    (["demo", "--trials", "0"], "--trials"),
    (["solve", "arm2", "--method", "dense"], "--method"),
    (["perturb", "point_mass", "--delay", "0.03", "--sensory-delays", "0,0.025"], "--sensory-delays"),
    (["perturb", "point_mass", "--delay", "0.03", "--pulse-time", "0.6"], "--pulse-time"),
    (["perturb", "pendulum"], "MODEL"),
    (["perturb", "point_mass", "--kick", "0"], "--kick"),
])
def test_bad_arguments_exit_with_2_and_say_why(args, message):
    result = CliRunner().invoke(cli.main, args)
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Error" in result.output


def test_delay_error_names_the_option():
    result = CliRunner().invoke(cli.main, ["compare", "arm2", "--delays", "0,0.025"])
    assert "Invalid value for --delays" in result.output and "got 0.025 s (2.5 steps)" in result.output


@pytest.mark.parametrize("command", sorted(cli.main.commands))
def test_help_documents_every_option(command):
    cmd = cli.main.commands[command]
    result = CliRunner().invoke(cli.main, [command, "--help"])
    assert result.exit_code == 0
    options = [p for p in cmd.params if p.param_type_name == "option"]
    for param in options:
        for opt in param.opts + param.secondary_opts:
            assert opt in result.output, (command, opt)
        if param.name != "help":
            assert param.help, (command, param.name)
    assert (cmd.help or "").strip()
    top = CliRunner().invoke(cli.main, ["--help"])
    assert command in top.output


FACTORY = """
import jax.numpy as jnp
import delayed_ilqr as di
from delayed_ilqr.models import point_mass


def reach(delay=0.0, noise=False, dt=0.01, target=(0.2, 0.1), stiffness=0.0):
    \"\"\"A point mass on a spring, reaching to target.\"\"\"
    base = point_mass(delay=delay, noise=noise, dt=dt, x_target=tuple(target) + (0.0, 0.0))

    def spring(x, u, ud):
        return base.dynamics(x, u, ud) - stiffness * jnp.concatenate([jnp.zeros(2), x[:2]])

    return base.replace(dynamics=_cached(spring, stiffness), name="spring_reach")


_CACHE = {}


def _cached(f, key):          # one function object per stiffness: one compilation
    return _CACHE.setdefault(key, f)


def not_a_problem(delay=0.0, noise=False):
    return 42
"""


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """A module file in the current folder, as a user would write it (a fresh name per test)."""
    name = f"user_models_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text(FACTORY)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(__import__("sys").path))     # the CLI adds the folder; undone here
    return name


def test_own_model_with_params_solves_like_the_api(user_module, tmp_path):
    out = tmp_path / "out"
    result = run("solve", f"{user_module}:reach", "--param", "target=(0.1, -0.05)", "--param", "stiffness=4.0",
                 "--delay", "0.02", "--no-noise", "--out", out)
    assert result.exit_code == 0, result.output
    assert "A point mass on a spring, reaching to target." in result.output
    module = __import__(user_module)
    reference = di.solve(module.reach(delay=0.02, target=(0.1, -0.05), stiffness=4.0))
    saved = di.load(out / "solution.npz")
    np.testing.assert_allclose(saved.u, reference.u, rtol=1e-12)
    assert float(np.linalg.norm(np.asarray(saved.x[-1, :2]) - [0.1, -0.05])) < 1e-2
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["settings"]["params"] == dict(target=[0.1, -0.05], stiffness=4.0)
    assert manifest["settings"]["model"] == f"{user_module}:reach"


def test_own_model_that_returns_no_problem_is_refused(user_module):
    result = CliRunner().invoke(cli.main, ["solve", f"{user_module}:not_a_problem"])
    assert result.exit_code == 2 and "the factory must return a delayed_ilqr.Problem" in result.output


def test_dt_makes_delays_between_the_default_steps_possible(tmp_path):
    """25 ms is 2.5 steps of the default 10 ms and is refused; at --dt 0.005 it is 5 steps."""
    assert run("solve", "point_mass", "--delay", "0.025").exit_code == 2
    result = run("solve", "point_mass", "--delay", "0.025", "--dt", "0.005", "--out", tmp_path)
    assert result.exit_code == 0, result.output
    meta = di.load_metadata(tmp_path / "solution.npz")
    assert (meta["dt"], meta["delay_steps"], meta["horizon"]) == (0.005, 5, 120)
    reference = di.solve(point_mass(delay=0.025, dt=0.005, noise=True))     # solve's default: --noise on
    np.testing.assert_allclose(di.load(tmp_path / "solution.npz").u, reference.u, rtol=1e-12)


def test_a_user_module_that_fails_to_import_is_a_usage_error(tmp_path, monkeypatch):
    """A syntax error, or an exception raised while the module runs, names the module and the
    error (exit code 2, no traceback)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(__import__("sys").path))
    name = f"broken_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text("def reach(delay=0.0, noise=False:\n    pass\n")
    (tmp_path / f"{name}_raises.py").write_text("raise RuntimeError('needs a licence file')\n")
    for module, what in ((name, "SyntaxError"), (f"{name}_raises", "RuntimeError: needs a licence file")):
        result = CliRunner().invoke(cli.main, ["solve", f"{module}:reach"])
        assert result.exit_code == 2, result.output
        assert f"cannot import module {module!r}" in result.output and what in result.output, result.output
        assert "Traceback" not in result.output


def test_no_command_prints_the_help_and_exits_0():
    result = CliRunner().invoke(cli.main, [])
    assert result.exit_code == 0, result.output
    assert "Usage:" in result.output and "Commands:" in result.output and "sweep" in result.output


def test_sweep_without_its_extra_says_how_to_install_it(tmp_path, monkeypatch):
    for module in ("xarray", "zarr"):
        monkeypatch.setitem(__import__("sys").modules, module, None)      # as if not installed
        result = CliRunner().invoke(cli.main, ["sweep", "point_mass", "--grid", "delay=0,0.03",
                                               "--out", tmp_path / "out"])
        assert result.exit_code == cli.ERROR_EXIT, result.output
        assert "pip install 'delayed-ilqr[sweep]'" in result.output and module in result.output, result.output
        assert "Traceback" not in result.output and not (tmp_path / "out").exists()
        monkeypatch.undo()
