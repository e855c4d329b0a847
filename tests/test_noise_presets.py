"""Noise presets and defaults: ``noise=True`` is the human preset of the human models, the
benchmark stress level only by name (``noise="benchmark"``), one default across the commands, and
the noise recorded in every output file."""
import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

import delayed_ilqr as di
from delayed_ilqr import cli
from delayed_ilqr.experiments.records import problem_record
from delayed_ilqr.models import arm2, arm2_muscle6, point_mass
from delayed_ilqr.models.arm2 import ACTIVATION_TIME, HUMAN_TORQUE_CV, SIGMA_U_HUMAN


def _p2_mass_matrix(q):
    """M(q) of P2 as the benchmark definition writes it (docs/models.md §2), by hand."""
    m2, l1, s2, I1, I2 = 1.1, 0.30, 0.16, 0.025, 0.045
    a1, a2, a3 = I1 + I2 + m2 * l1 ** 2, m2 * l1 * s2, I2
    c2 = math.cos(q[1])
    return np.array([[a1 + 2 * a2 * c2, a3 + a2 * c2], [a3 + a2 * c2, a3]])


def test_the_benchmark_preset_is_p2_noisy_as_defined():
    """noise="benchmark" reproduces P2-noisy: F = [0; M(q)^{-1} 0.2 diag(ud)], p = 2, on P2's
    grid, start, target and cost; P3 and the P1-noisy preset likewise (the definitions of
    docs/models.md §2, written out here)."""
    rng = np.random.default_rng(7)
    for delay, steps in ((0.0, 0), (0.03, 3), (0.1, 10)):
        p = arm2(delay=delay, noise="benchmark")
        assert (p.dt, p.horizon, p.delay_steps, p.n_noise) == (0.01, 50, steps, 2)
        assert p.metadata.noise == "benchmark"
    np.testing.assert_allclose(p.x0, [math.pi / 4, math.pi / 2, 0, 0], rtol=0, atol=0)
    np.testing.assert_allclose(p.cost.x_target, [math.pi / 2, math.pi / 3, 0, 0], rtol=0, atol=0)
    np.testing.assert_array_equal(p.cost.P, np.zeros((4, 4)))
    np.testing.assert_array_equal(p.cost.Q, 1e-4 * np.eye(2))
    np.testing.assert_array_equal(p.cost.P_final, np.diag([1e3, 1e3, 1e1, 1e1]))
    for _ in range(3):
        x, u, ud = rng.normal(size=4), rng.normal(size=2), rng.normal(size=2)
        expected = np.vstack([np.zeros((2, 2)), np.linalg.solve(_p2_mass_matrix(x[:2]), 0.2 * np.diag(ud))])
        np.testing.assert_allclose(np.asarray(p.noise(x, u, ud)), expected, rtol=1e-12, atol=1e-15)
    p3 = arm2(dt=0.002, delay=0.1, noise="benchmark")
    assert (p3.horizon, p3.delay_steps) == (250, 50)
    p1 = point_mass(noise="benchmark")
    assert p1.metadata.noise == "benchmark" and p1.noise == point_mass(noise=True).noise
    x, ud = rng.normal(size=4), rng.normal(size=2)
    F = np.zeros((4, 4))
    F[2, 0], F[3, 1], F[2, 2], F[3, 3] = 0.5 * ud[0], 0.5 * ud[1], 0.05, 0.05
    np.testing.assert_allclose(np.asarray(p1.noise(x, ud, ud)), F, rtol=1e-12, atol=1e-15)


def test_noise_true_is_the_human_preset_on_the_arms():
    human = arm2(noise=True)
    assert human.metadata.noise == "human" and human.noise.sigma_u == SIGMA_U_HUMAN
    assert arm2(noise="human").noise == human.noise
    assert arm2_muscle6(noise=True).metadata.noise == "human"
    assert arm2(noise=True, sigma_u=0.05).metadata.noise == "custom"
    assert arm2().noise is None and arm2().metadata.noise is None       # P2 stays deterministic


def test_the_human_preset_has_the_stated_torque_cv():
    """HUMAN_TORQUE_CV is the CV of a held torque low-pass filtered at the activation time constant:
    the model's own torque noise (M(q) times the velocity rows of its F) filtered by Euler steps of
    1 ms over 4000 independent trials, against the closed form sigma_u / sqrt(2 t) = 3.2 %."""
    assert HUMAN_TORQUE_CV == pytest.approx(0.0316, abs=1e-4)
    p = arm2(noise=True, dt=0.001)
    x = np.asarray(p.x0)
    tau = np.array([2.0, -1.0])                                     # a held torque, N m
    F = np.asarray(p.noise(x, tau, tau))[2:]                        # [2, 2]: velocity rows
    G = _p2_mass_matrix(x[:2]) @ F                                  # torque noise per unit dw
    rng = np.random.default_rng(0)
    a, y = p.dt / ACTIVATION_TIME, np.tile(tau, (4000, 1))
    for _ in range(1500):                                           # 30 time constants: stationary
        torque = tau + rng.standard_normal((4000, 2)) @ G.T / math.sqrt(p.dt)
        y = y + a * (torque - y)
    cv = y.std(axis=0) / np.abs(tau)
    # the Euler filter's stationary variance is 2 / (2 - a) times the continuous one (+0.5 % in SD)
    np.testing.assert_allclose(cv, HUMAN_TORQUE_CV * math.sqrt(2 / (2 - a)), rtol=0.04)


@pytest.mark.parametrize("kwargs, message", [
    (dict(noise="loud"), "noise must be True, False or a noise preset of arm2 ('human', 'benchmark')"),
    (dict(noise="benchmark", sigma_u=0.01), "sigma_u must be None with noise='benchmark'"),
    (dict(noise=True, sigma_u=-0.1), "sigma_u"),
    (dict(noise=1), "noise must be True or False"),
])
def test_bad_noise_arguments_are_refused(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message.replace("(", r"\(").replace(")", r"\)")):
        arm2(**kwargs)


def test_the_point_mass_has_no_human_preset():
    with pytest.raises(ValueError, match="noise preset of point_mass"):
        point_mass(noise="human")


CAPTURE = """
import json, os


class Captured(Exception):
    pass


def factory(delay=0.0, noise=False, **kwargs):
    with open(os.environ["NOISE_CAPTURE"], "a") as f:
        f.write(json.dumps(noise) + "\\n")
    raise Captured("captured")
"""


@pytest.mark.parametrize("extra, expected", [([], True), (["--no-noise"], False),
                                             (["--noise", "benchmark"], "benchmark")])
def test_solve_simulate_compare_and_perturb_share_one_noise_default(tmp_path, monkeypatch, extra, expected):
    """Every command hands the model's factory the same noise: by default True (the model's own
    default preset), --no-noise False, a preset by name."""
    name = f"capture_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text(CAPTURE)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.path", list(__import__("sys").path))
    capture = tmp_path / "noise.jsonl"
    monkeypatch.setenv("NOISE_CAPTURE", str(capture))
    for command in ("solve", "simulate", "compare"):
        CliRunner().invoke(cli.main, [command, f"{name}:factory"] + extra)
    seen = [json.loads(line) for line in capture.read_text().splitlines()]
    assert seen == [expected] * 3
    defaults = {c: next(p for p in cli.main.commands[c].params if p.name == "noise").default
                for c in ("solve", "simulate", "compare", "perturb")}
    assert set(defaults.values()) == {"on"}


def test_a_preset_the_model_lacks_is_a_usage_error_naming_noise():
    result = CliRunner().invoke(cli.main, ["solve", "point_mass", "--noise", "human"])
    assert result.exit_code == 2 and "'--noise'" in result.output and "noise preset of point_mass" in result.output
    result = CliRunner().invoke(cli.main, ["solve", "arm2", "--noise", "benchmark", "--no-noise"])
    assert result.exit_code == 2 and "--no-noise" in result.output


@pytest.mark.parametrize("noise, preset, sigma_u", [(None, "human", 0.01), ("benchmark", "benchmark", 0.2)])
def test_the_manifest_and_the_saved_solution_record_the_problem(tmp_path, noise, preset, sigma_u):
    """solve's manifest, solution.json and the header of solution.npz carry the problem's record:
    the noise preset and level, the delay, dt, horizon and the arm's parameters."""
    args = ["solve", "arm2", "--delay", "0.03", "--param", "horizon=12", "--out", tmp_path]
    result = CliRunner().invoke(cli.main, [str(a) for a in args + ([] if noise is None else ["--noise", noise])])
    assert result.exit_code in (0, 1), result.output
    manifest = json.loads((tmp_path / "manifest.json").read_text())["settings"]["problem"]
    solution = json.loads((tmp_path / "solution.json").read_text())["problem"]
    header = di.load_metadata(tmp_path / "solution.npz")["info"]["problem"]
    expected = problem_record(arm2(delay=0.03, horizon=12, noise=True if noise is None else noise))
    for record in (manifest, solution, header):
        assert record == json.loads(json.dumps(expected))
        assert record["noise"]["preset"] == preset and record["noise"]["sigma_u"] == sigma_u
        assert (record["dt"], record["horizon"], record["delay"], record["delay_steps"]) == (0.01, 12, 0.03, 3)
        assert record["dynamics"]["params"]["m2"] == 1.1 and record["dynamics"]["params"]["b11"] == 0.05
