"""The gallery's analysis functions on synthetic data whose answer is known, and each experiment
end to end at a small size on the torque-driven arm, asserting its physics (causality first)."""
import math

import numpy as np
import pytest

from delayed_ilqr.experiments import responses


# -- analysis functions on known data ------------------------------------------------------------

def test_first_change_finds_a_known_step_in_one_trial_of_many():
    diff = np.zeros((5, 40, 2))
    diff[3, 17:, 1] = 1e-4                  # one trial, one command, from step 17 on
    diff[:, 30:, :] += 0.5
    assert responses.first_change(diff) == 17
    assert responses.first_change(diff, start=20) == 20       # trial 3 still differs there
    assert responses.first_change(diff[[0, 1, 2, 4]]) == 30
    assert responses.first_change(np.zeros((3, 10))) is None


def test_onset_of_a_noisy_step_is_the_step_and_round_off_is_not_a_change():
    rng = np.random.default_rng(1)
    k = np.arange(100)
    signal = np.where(k >= 42, 1.0, 0.0) + 0.02 * rng.standard_normal(100)   # noise below 10 % of the peak
    assert responses.onset(signal) == 42
    ramp = np.clip((k - 50) / 20.0, 0.0, 1.0)                                  # reaches 10 % at k = 52
    assert responses.onset(ramp) == 52
    assert responses.onset(ramp, threshold=0.5) == 60
    assert responses.onset(np.zeros(10)) is None
    assert responses.first_change(np.where(k >= 42, 1.0, 1e-14)) == 42
    with pytest.raises(ValueError, match="threshold must lie in"):
        responses.onset(ramp, threshold=0.0)


@pytest.mark.parametrize("angle", [0.0, 0.3, math.pi / 2, -1.2])
def test_ellipse_of_a_known_covariance(angle):
    R = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    cov = R @ np.diag([9.0, 1.0]) @ R.T
    e = responses.ellipse(cov)
    assert e.major == pytest.approx(3.0) and e.minor == pytest.approx(1.0)
    expected = angle if -math.pi / 2 < angle <= math.pi / 2 else angle - math.copysign(math.pi, angle)
    assert e.angle == pytest.approx(expected)
    with pytest.raises(ValueError, match="cov must be a finite"):
        responses.ellipse(np.eye(3))


def test_axis_sd_projects_on_the_direction():
    rng = np.random.default_rng(0)
    pts = rng.standard_normal((20000, 2)) * [2.0, 0.5]
    assert responses.axis_sd(pts, [1, 0]) == pytest.approx(2.0, rel=0.03)
    assert responses.axis_sd(pts, [0, 3]) == pytest.approx(0.5, rel=0.03)


def test_fitts_fit_recovers_an_exact_line_and_r2_drops_with_scatter():
    d, w = np.meshgrid([0.05, 0.1, 0.2], [0.005, 0.01, 0.02], indexing="ij")
    index = responses.index_of_difficulty(d, w)
    assert index[1, 1] == pytest.approx(math.log2(20))
    fit = responses.fitts_fit(index, 0.12 + 0.15 * index)
    assert fit.a == pytest.approx(0.12) and fit.b == pytest.approx(0.15) and fit.r2 == pytest.approx(1.0)
    noisy = 0.12 + 0.15 * index + np.array([0.05, -0.05, 0.0] * 3).reshape(3, 3)
    assert responses.fitts_fit(index, noisy).r2 < 0.99
    with pytest.raises(ValueError, match="at least 3 finite pairs"):
        responses.fitts_fit([1.0, 2.0, np.nan], [0.1, 0.2, 0.3])


def test_shortest_meeting_interpolates_where_the_margin_crosses_zero():
    t = np.array([0.2, 0.3, 0.4, 0.5])
    assert responses.shortest_meeting(t, [-3.0, -1.0, 1.0, 2.0]) == pytest.approx(0.35)
    assert responses.shortest_meeting(t, [1.0, 1.0, 1.0, 1.0]) == pytest.approx(0.2)
    assert math.isnan(responses.shortest_meeting(t, [-1.0, -1.0, 1.0, -0.5]))
    # met, lost, met again: the time from which it stays met
    assert responses.shortest_meeting(t, [1.0, -1.0, 1.0, 1.0]) == pytest.approx(0.35)


def test_the_fitts_criterion_is_the_effective_width():
    from delayed_ilqr.experiments.fitts import criterion_margin
    sd = 0.01 / responses.EFFECTIVE_WIDTH_SD
    assert criterion_margin(0.0, sd, 0.01) == pytest.approx(0.0, abs=1e-15)
    assert criterion_margin(0.001, sd, 0.01) == pytest.approx(-0.001)


def test_minimal_intervention_ratio_of_a_known_scatter():
    from delayed_ilqr.experiments.minimal_intervention import analyse
    rng = np.random.default_rng(2)
    pts = rng.standard_normal((20000, 2)) * [3.0, 1.0]          # 3x wider along x
    s = analyse("bar", pts, [1.0, 0.0])
    assert s.ratio == pytest.approx(3.0, rel=0.03)
    assert abs(s.ellipse.angle) < 0.05


# -- end to end, small, on the torque-driven arm -------------------------------------------------

def test_kick_never_responds_before_the_loop_latency_and_ends_finite():
    from delayed_ilqr.experiments.kick import kick_experiment
    r = kick_experiment("arm2", delay=0.03, sensory_delay=0.02, kick=0.15, trials=8, final_time=0.4)
    a = r.analysis
    assert r.solution.converged
    assert a.loop_latency == pytest.approx(0.05)
    # causality: the first command that can see x_{kp+1} is issued l_s steps later and acts l_m later
    assert a.first_change is not None and a.first_change >= a.loop_latency - 1e-12
    assert a.first_change == pytest.approx(a.loop_latency)          # and with common noise it does respond then
    assert a.onset >= a.first_change
    assert np.all(np.isfinite(r.kicked.errors)) and a.peak_displacement > 0.005
    # before the kick acts the runs are identical
    kp = r.pulse_step
    np.testing.assert_array_equal(np.asarray(r.kicked.runs.x)[:, :kp + 1], np.asarray(r.base.runs.x)[:, :kp + 1])
    from delayed_ilqr.plot.gallery import plot_kick
    fig = plot_kick(r)
    line = next(l for l in fig.axes[1].lines if l.get_label().startswith("model"))
    t, resp = line.get_data()
    assert np.all(resp[t < 1e3 * a.loop_latency - 1e-9] == 0)         # the figure shows the causal bound too


def test_target_jump_correction_waits_for_the_delay_and_an_early_jump_reaches_the_new_target():
    from delayed_ilqr.experiments.target_jump import target_jump_experiment
    r = target_jump_experiment("arm2", delay=0.05, jump=0.02, times_before_end=(0.04, 0.3), trials=5,
                               final_time=0.5)
    late, early = r.analyses
    assert r.solution.converged
    # a jump 40 ms before the end, with a 50 ms loop: no command that sees it acts before the end
    assert late.first_change is None or late.first_change >= late.loop_latency
    assert late.corrected < 0.05
    assert early.first_change == pytest.approx(early.loop_latency)
    assert early.error_new.median < 0.01 and early.corrected > 0.8


def test_minimal_intervention_and_fitts_run_end_to_end():
    from delayed_ilqr.experiments.fitts import fitts_experiment
    from delayed_ilqr.experiments.minimal_intervention import minimal_intervention_experiment
    point, bar = minimal_intervention_experiment("arm2", delay=0.03, sensory_delay=None, trials=30, final_time=0.4)
    assert point.status.startswith("CONVERGED") and bar.status.startswith("CONVERGED")
    assert np.isfinite(point.ratio) and np.isfinite(bar.ratio)
    (r,) = fitts_experiment("arm2", distances=(0.04, 0.16), widths=(0.002, 0.02), movement_times=(0.2, 0.3, 0.4),
                            delays=(0.03,), sensory_delay=0.02, hold=0.05, trials=20)
    assert r.sd.shape == (2, 3) and np.all(np.isfinite(r.sd))
    # the 4x longer reach needs more force: more signal-dependent noise (about 2x the SD, measured at
    # 60 trials; 20 trials estimate an SD within about 16 %)
    assert r.sd[1].mean() > 1.3 * r.sd[0].mean()
    # a wider target is never slower to meet
    met = np.isfinite(r.mt[:, 0])
    assert np.all(r.mt[met, 1] <= r.mt[met, 0])


def test_target_jump_command_writes_an_atomic_folder_with_its_manifest(tmp_path):
    import json

    from click.testing import CliRunner

    from delayed_ilqr import cli
    out = tmp_path / "jump"
    result = CliRunner().invoke(cli.main, ["--no-cache", "target-jump", "--delay", "0.05", "--times", "0.04,0.3",
                                           "--final-time", "0.5", "--trials", "3", "--out", str(out)],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert "Liu & Todorov 2007" in result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(manifest["files"]) == {"target_jump.json", "target_jump.md", "target_jump.png"}
    data = json.loads((out / "target_jump.json").read_text())
    late, early = data["analyses"]
    assert early["first_change"] == pytest.approx(0.05) and early["error_new"]["median"] < 0.01
    bad = CliRunner().invoke(cli.main, ["target-jump", "--times", "0.7", "--final-time", "0.6"])
    assert bad.exit_code == 2 and "--times" in bad.output
