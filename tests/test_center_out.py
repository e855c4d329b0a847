"""The center-out study of the six-muscle arm: convergence to every target at every delay, the delay
gains doing their job in noise, and the ``center-out`` command's files."""
import json

import jax
import numpy as np
from click.testing import CliRunner

import delayed_ilqr as di
from delayed_ilqr import center_out as co
from delayed_ilqr import cli
from delayed_ilqr.models import arm2_muscle6


def test_reaches_converge_to_all_eight_targets_at_each_delay():
    results = co.center_out(delays=(0.0, 0.05, 0.1), n_targets=8, n_trials=10)
    report = co.format_table(results)
    print("\n" + report)
    for r in results:
        for j, t in enumerate(r.targets):
            assert t.converged, (r.delay, j, t.status)
            # the nominal ends on the target (w_p = 1/m^2 against r = 1e-4: sub-millimetre)
            assert t.hand_error < 1e-3, (r.delay, j, t.hand_error)
            assert np.all((np.asarray(r.solutions.u[j]) >= 0.0) & (np.asarray(r.solutions.u[j]) <= 1.0))
        assert r.delay_steps == round(r.delay / 0.01)
    records = json.loads(json.dumps(co.to_records(results)))
    assert [len(r["targets"]) for r in records] == [8, 8, 8]


def _median_error(problem, policy, target, n_trials=100):
    runs = di.simulate(problem, policy, n_trials, seed=3)
    return float(np.median(np.linalg.norm(co._hand(runs.x[:, -1]) - target, axis=1)))


def test_delay_feedback_keeps_noisy_reaches_on_target():
    """At 50 ms and small excitation noise, the full delayed law beats both the open-loop nominal and
    the same law without the feedback on commands in flight (M = 0): the delay gains matter."""
    result = co.center_out(delays=(0.05,), n_targets=1, n_trials=2)[0]
    policy, target = result.policy(0), result.targets[0].target
    plant = arm2_muscle6(delay=0.05, target=tuple(target), noise=True, sigma_u=0.01)
    closed = _median_error(plant, policy, target)
    no_m = _median_error(plant, policy._replace(delay_feedback=jax.numpy.zeros_like(policy.delay_feedback)), target)
    open_loop = _median_error(plant, policy._replace(state_feedback=0 * policy.state_feedback,
                                                     delay_feedback=0 * policy.delay_feedback), target)
    print(f"\nmedian hand error at 50 ms, sigma_u 0.01: full law {1e3 * closed:.2f} mm, M = 0 "
          f"{1e3 * no_m:.2f} mm, open loop {1e3 * open_loop:.2f} mm")
    assert closed < open_loop / 3
    assert closed < no_m / 3


def test_center_out_command_writes_its_report(tmp_path):
    out = tmp_path / "co"
    result = CliRunner().invoke(cli.main, ["center-out", "--delays", "0", "--targets", "2", "--trials", "4",
                                           "--out", str(out)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    data = json.loads((out / "center_out.json").read_text())
    assert data["settings"]["targets"] == 2 and len(data["results"][0]["targets"]) == 2
    for name in ("center_out.md", "center_out_hand_paths.png", "center_out_excitations_0ms.png"):
        assert (out / name).stat().st_size > 0
    assert "2/2" in result.output


def test_center_out_command_refuses_a_delay_off_the_grid():
    result = CliRunner().invoke(cli.main, ["center-out", "--delays", "0.005"])
    assert result.exit_code == 2
    assert "--delays" in result.output
