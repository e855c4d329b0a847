"""The README is the front page: short, and everything it shows works. Its Python blocks run in
order in one namespace, as a reader would paste them, and what they print holds (the solves
converge, the predictions agree with the Monte Carlo); its shell commands exist; its model table
is the model zoo."""
import contextlib
import io
import pathlib
import re

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).parents[1]
README = (ROOT / "README.md").read_text()


def _blocks(language):
    return re.findall(rf"^```{language}\n(.*?)^```", README, re.S | re.M)


def test_readme_is_a_front_page():
    assert len(README.splitlines()) <= 200
    assert len(_blocks("python")) >= 4


@pytest.fixture(scope="module")
def namespace():
    namespace = {"__name__": "readme"}
    with contextlib.redirect_stdout(io.StringIO()):
        for j, code in enumerate(_blocks("python")):
            exec(compile(code, f"README.md (python block {j + 1})", "exec"), namespace)
    return namespace


def test_five_line_solve_converges(namespace):
    sol = namespace["sol"]                  # the second block's noisy point mass
    assert sol.converged, sol.message


def test_noisy_prediction_within_the_monte_carlo_interval(namespace):
    """The policy's exact expected cost on its LQG model lies inside the 95 % bootstrap interval of
    500 trials on the plant (the point mass is linear: the prediction is exact up to sampling)."""
    low, high = namespace["runs"].summary().ci95
    assert low <= float(namespace["sol"].expected_cost) <= high


def test_own_plant_reaches_its_target(namespace):
    mine = namespace["mine"]
    assert mine.converged, mine.message
    assert abs(float(mine.x[-1, 0]) - 0.5) < 0.02


def test_sensors_cost_more_and_the_monte_carlo_agrees(namespace):
    """Seeing the position only, 50 ms late and through noise, costs more than seeing the state at
    once; the Monte Carlo of the filter on the plant agrees with the pair's exact expected cost."""
    import delayed_ilqr as di
    blind, seen = namespace["blind"], namespace["seen"]
    assert blind.converged, blind.message
    assert float(blind.expected_cost) > 1.2 * float(namespace["sol"].expected_cost)
    summary = di.simulate(seen, blind.policy, 500, seed=0).summary()
    assert abs(summary.mean_cost - float(blind.expected_cost)) <= 4 * summary.standard_error


def test_shell_commands_exist():
    """`make` targets are the Makefile's; `delayed-ilqr` commands are the command line's (their
    options are checked for every page by tests/test_docs.py)."""
    from delayed_ilqr.cli import main
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    lines = [line.split("#")[0].split() for block in _blocks("bash") for line in block.splitlines()]
    lines = [words for words in lines if words]
    assert lines
    for words in lines:
        if words[0] == "make":
            assert words[1] in targets, words
        elif words[0] == "delayed-ilqr":
            assert words[1] in main.commands, words
        else:
            assert words[:2] == ["pip", "install"], words


def test_model_table_is_the_zoo():
    from delayed_ilqr import models
    rows = re.findall(r"^\| `(\w+)` \| [^|]+ \| (\d+) / (\d+) \|$", README, re.M)
    assert {name for name, _, _ in rows} == set(models.REGISTRY)
    for name, n, d in rows:
        problem = getattr(models, name)()
        assert (problem.x0.shape[0], problem.n_controls) == (int(n), int(d)), name


def test_mpc_reaches_the_waypoint(namespace):
    run = namespace["run"]                  # the MPC block: the quadrotor with 80 ms of latency
    assert not np.any(run.failed) and not np.any(run.diverged)
    np.testing.assert_allclose(np.asarray(run.x)[:, -1, :2], [[1.0, 0.5]], atol=0.02)
