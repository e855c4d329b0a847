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


def test_believed_fraction_projects_the_estimate_on_the_true_shift():
    true = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    believed = np.array([[0.0, 0.0], [0.5, 1.0], [1.0, 1.0]])
    assert responses.believed_fraction(true, believed, 1) == pytest.approx(0.25)     # the part along the shift
    assert responses.believed_fraction(true, believed, 2) == pytest.approx(0.5)
    assert responses.believed_fraction(true, true, 2) == pytest.approx(1.0)
    assert math.isnan(responses.believed_fraction(true, believed, 0))


def test_disturbance_model_adds_external_torques_to_the_design_only():
    import jax.numpy as jnp

    from delayed_ilqr.models.arm2 import mass_matrix_inverse
    from delayed_ilqr.models.arm2_muscle6 import arm2_muscle6, with_disturbance_model
    plant = arm2_muscle6()
    design = with_disturbance_model(plant, 0.05)
    x, u = plant.x0, jnp.full(6, 0.2)
    F, Fd = np.asarray(plant.noise(x, u, u)), np.asarray(design.noise(x, u, u))
    assert Fd.shape == (10, F.shape[1] + 2)
    np.testing.assert_array_equal(Fd[:, :-2], F)                # the plant's own columns unchanged
    expected = np.zeros((10, 2))
    expected[2:4] = 0.05 * np.asarray(mass_matrix_inverse(x[:2]))
    np.testing.assert_allclose(Fd[:, -2:], expected, rtol=1e-12)
    assert plant.noise is not design.noise and design.observation is plant.observation
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="sigma_d must be a positive density"):
            with_disturbance_model(plant, bad)


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


def test_json_ready_makes_strict_json_of_numbers_arrays_and_statistics():
    import json

    import jax.numpy as jnp

    from delayed_ilqr.experiments.report import json_ready
    from delayed_ilqr.statistics import sample_stats
    data = json_ready(dict(a=float("nan"), b=np.array([1.0, np.inf]), c=jnp.asarray(2.5), d=(np.int64(3), None),
                           e=sample_stats(np.array([1.0, 2.0, 3.0])), f="text"))
    assert data["a"] is None and data["b"] == [1.0, None] and data["c"] == 2.5 and data["d"] == [3, None]
    assert data["e"]["median"] == 2.0 and data["f"] == "text"
    json.dumps(data, allow_nan=False)                           # strict: raises on a NaN left behind


def test_target_state_with_sensors_sees_the_target_as_late_as_the_arm():
    from delayed_ilqr.experiments import reach_tasks
    base = reach_tasks.reach("arm2", delay=0.02, sensory_delay=0.04)
    plant, design = reach_tasks.with_target_state(base), reach_tasks.with_target_state(base, 0.02)
    obs = plant.observation
    assert plant.n_states == 6 and obs.delay_steps == base.observation.delay_steps
    np.testing.assert_array_equal(np.asarray(obs.H)[-2:], np.c_[np.zeros((2, 4)), np.eye(2)])
    np.testing.assert_array_equal(np.asarray(obs.H)[:-2, :4], np.asarray(base.observation.H))
    x, u = np.asarray(plant.x0), np.zeros(2)
    assert plant.noise(x, u, u).shape == (6, 2)                 # the plant's target moves only when jumped
    F = np.asarray(design.noise(x, u, u))
    np.testing.assert_allclose(F[-2:, -2:], 0.02 * np.eye(2))  # the design expects it to move
    assert reach_tasks.loop_latency(plant) == pytest.approx(0.06)
    with pytest.raises(ValueError, match="target_motion must be"):
        reach_tasks.with_target_state(base, -1.0)


# -- the findings, on the six-muscle arm with its defaults --------------------------------------
# Each experiment runs once per module (module-scoped fixtures) at a size that resolves its
# assertion; the full-size runs are the `full` tests at the end (make bench) and the docs' commands.
# A finding the defaults do not reproduce yet is marked xfail(strict=True) with what was measured:
# its published range stays, and the mark must go when the defaults reproduce it.

ARM = "arm2_muscle6"
SEED = 0


@pytest.fixture(scope="module")
def kick_result():
    from delayed_ilqr.experiments.kick import kick_experiment
    return kick_experiment(ARM, trials=20, seed=SEED)


@pytest.fixture(scope="module")
def jump_result():
    from delayed_ilqr.experiments.target_jump import target_jump_experiment
    return target_jump_experiment(ARM, times_before_end=(0.1, 0.2, 0.3), trials=20, seed=SEED)


@pytest.fixture(scope="module")
def scatter_result():
    from delayed_ilqr.experiments.minimal_intervention import minimal_intervention_experiment
    return minimal_intervention_experiment(ARM, trials=150, seed=SEED)


def test_kick_response_starts_at_the_loop_latency_measured_from_the_commands(kick_result):
    from delayed_ilqr.experiments.reach_tasks import loop_latency
    a = kick_result.analysis
    assert kick_result.solution.converged
    assert a.loop_latency == pytest.approx(loop_latency(kick_result.problem)) and a.loop_latency > 0
    # causality, then the measurement: the first applied command that differs (any trial, common noise)
    assert a.first_change is not None and a.first_change == pytest.approx(a.loop_latency)
    assert a.onset >= a.first_change
    # the filter's belief is measured one and two loop latencies after the kick (the docs' cause)
    assert len(a.believed) == 2 and all(np.isfinite(a.believed))
    assert 0 < a.believed[0] < a.believed[1]                    # the filter comes to believe the kick
    kp = kick_result.pulse_step
    np.testing.assert_array_equal(np.asarray(kick_result.kicked.runs.x)[:, :kp + 1],
                                  np.asarray(kick_result.base.runs.x)[:, :kp + 1])
    from delayed_ilqr.plot.gallery import plot_kick
    line = next(l for l in plot_kick(kick_result).axes[1].lines if l.get_label().startswith("model"))
    t, resp = line.get_data()
    assert np.all(resp[t < 1e3 * a.loop_latency - 1e-9] == 0)


def test_replanning_leaves_the_unperturbed_reach_as_the_fixed_law_makes_it(kick_result):
    """The model's controller re-plans at every tick; without a perturbation its reach keeps the
    fixed law's endpoint scatter and speed profile (their own trials on the same seed)."""
    from delayed_ilqr.experiments.replanning import reach_profile
    assert kick_result.controller == "replanning" and kick_result.solver_failures == 0
    dt = kick_result.problem.dt
    replanned, fixed = reach_profile(kick_result.base, dt), reach_profile(kick_result.fixed_base, dt)
    assert 0.67 < replanned.sd_major / fixed.sd_major < 1.5, (replanned, fixed)
    assert replanned.peak_over_mean == pytest.approx(fixed.peak_over_mean, rel=0.05)
    assert replanned.time_to_peak == pytest.approx(fixed.time_to_peak, abs=0.05)


KICK_NOT_YET = pytest.mark.xfail(strict=True, reason=(
    "not reproduced with the six-muscle arm's defaults: median final error 26.2 mm kicked against 3.5 mm "
    "unperturbed with the re-planning controller (7.4x, 20 trials; the fixed law: 26.7 against 3.7 mm at 200; "
    "Nashed et al. 2012: within about 2x); with the state seen the same controller ends 0.7 mm off: the delayed "
    "filter does not believe the kick (docs/gallery/kick.md)"))


@KICK_NOT_YET
def test_kicked_hand_ends_within_twice_the_unperturbed_error(kick_result):
    a = kick_result.analysis
    assert a.peak_displacement > 0.005                          # the kick moved the hand
    assert a.error_ratio <= 2.0, (a.error_kicked.median, a.error_base.median)


# The six-muscle arm's jumps re-plan at every tick over three jump times: make bench. The suite holds
# the same experiment on the torque arm through the command line (reached within 1 cm, the first
# change at the loop latency: test_target_jump_command_writes_an_atomic_folder_with_its_manifest) and
# the fixed law's overshoot on the six-muscle arm below.
@pytest.mark.full
def test_target_jump_correction_starts_at_the_loop_latency(jump_result):
    assert jump_result.solution.converged
    for a in jump_result.analyses:
        assert a.first_change is not None and a.first_change == pytest.approx(a.loop_latency)
        assert a.believed is not None and np.isfinite(a.believed)      # the filter's belief is measured


@pytest.mark.full
def test_early_target_jumps_are_reached_and_late_ones_left_incomplete(jump_result):
    """Liu & Todorov 2007 with the model's re-planning controller: jumps 200 and 300 ms before the
    end are reached within 1 cm, the later the jump the less of it is made up (100 ms: almost none,
    the loop latency and the muscles' activation leave no time)."""
    late, mid, early = jump_result.analyses                   # 100, 200, 300 ms before the end
    assert jump_result.controller == "replanning" and jump_result.solver_failures == 0
    assert mid.error_new.median < 0.01 and early.error_new.median < 0.01, (mid.error_new, early.error_new)
    assert late.corrected < mid.corrected < early.corrected <= 1.05      # no overshoot
    assert mid.peak_speed > early.peak_speed                  # the later correction is the faster


def test_the_fixed_law_overshoots_a_late_target_jump():
    """The fixed time-varying law of one solve (``controller="fixed"``) overshoots a 2 cm jump 200 ms
    before the end (its corrections leave the linearisation; 236 % at 100 trials): the reason the
    model's controller re-plans."""
    from delayed_ilqr.experiments.target_jump import target_jump_experiment
    r = target_jump_experiment(ARM, times_before_end=(0.2,), trials=4, seed=SEED, controller="fixed")
    assert r.analyses[0].corrected > 1.5


def test_bar_target_scatters_along_the_bar(scatter_result):
    point, bar = scatter_result
    assert bar.status.startswith("CONVERGED")
    assert bar.ratio >= 1.5, (bar.irrelevant, bar.relevant)     # Todorov & Jordan 2002; Knill et al. 2011
    assert bar.ratio > point.ratio


def test_target_jump_command_writes_an_atomic_folder_with_its_manifest(tmp_path):
    import json

    from click.testing import CliRunner

    from delayed_ilqr import cli
    out = tmp_path / "jump"
    result = CliRunner().invoke(cli.main, ["--no-cache", "target-jump", "--arm", "arm2", "--delay", "0.05",
                                           "--sensory-delay", "none", "--times", "0.04,0.3", "--final-time", "0.5",
                                           "--trials", "3", "--out", str(out)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert "Liu & Todorov 2007" in result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(manifest["files"]) == {"target_jump.json", "target_jump.md", "target_jump.png"}
    assert manifest["settings"]["problem"]["delay_steps"] == 5
    assert manifest["settings"]["problem"]["n_states"] == 6          # the arm and the target
    data = json.loads((out / "target_jump.json").read_text())
    late, early = data["analyses"]
    assert early["first_change"] == pytest.approx(0.05) and early["error_new"]["median"] < 0.01
    # a jump 40 ms before the end with a 50 ms loop: no command that sees it acts before the end
    assert late["first_change"] is None and late["corrected"] < 0.05
    bad = CliRunner().invoke(cli.main, ["target-jump", "--times", "0.7", "--final-time", "0.6"])
    assert bad.exit_code == 2 and "--times" in bad.output
    for command in ("kick", "target-jump"):
        bad = CliRunner().invoke(cli.main, [command, "--disturbance-model", "0"])
        assert bad.exit_code == 2 and "--disturbance-model" in bad.output


@pytest.fixture(scope="module")
def fitts_result():
    from delayed_ilqr.experiments.fitts import DISTANCES, WIDTHS, fitts_experiment
    (r,) = fitts_experiment(ARM, distances=DISTANCES[:3], widths=WIDTHS,     # Fitts 1954's 2, 4, 8 in; 1-2 in
                            movement_times=(0.1, 0.15, 0.2, 0.25, 0.3, 0.4), delays=("model",), trials=40, seed=SEED)
    return r


def test_fitts_movement_time_is_linear_in_the_index_above_the_floor(fitts_result):
    from delayed_ilqr.experiments.fitts import criterion_margin
    r = fitts_result
    unfinished = np.array([[not s.startswith("CONVERGED") for s in row] for row in r.status])
    assert np.all(criterion_margin(r.bias, r.sd, max(r.widths))[unfinished] < 0), r.status   # none counts as met
    inside = np.isfinite(r.mt) & (r.mt > r.movement_times[0])
    assert inside.sum() >= 6, r.mt                              # enough conditions to fit
    assert r.fit is not None and r.fit.r2 >= 0.9, r.fit         # Fitts 1954: MT linear in log2(2D/W)
    assert r.fit.b > 0.05, r.fit                                # at least 50 ms/bit
    met = np.where(np.isfinite(r.mt), r.mt, np.inf)
    assert np.all(np.diff(met, axis=0) >= 0) and np.all(np.diff(met, axis=1) <= 0), r.mt   # farther, narrower: slower


FITTS_SLOPE_NOT_YET = pytest.mark.xfail(strict=True, reason=(
    "the slope is below the published range: 72 ms/bit at the model's delays over 1-2 in widths and 2-12 in "
    "amplitudes (100 trials; 70 ms/bit here: docs/gallery/fitts.md); 100-200 ms/bit in discrete pointing "
    "(MacKenzie 1992)"))
FITTS_FLOOR_NOT_YET = pytest.mark.xfail(strict=True, reason=(
    "the endpoint SD stops shrinking at 3-5 mm (the delayed filter's error in estimating the hand from "
    "proprioception): the narrowest width met is 13-20 mm, Fitts 1954's 0.25 in (6.35 mm) is never met: "
    "docs/gallery/fitts.md"))


@FITTS_SLOPE_NOT_YET
def test_fitts_slope_within_the_published_range(fitts_result):
    from delayed_ilqr.experiments.fitts import SLOPE_RANGE
    assert SLOPE_RANGE[0] <= fitts_result.fit.b <= SLOPE_RANGE[1], fitts_result.fit   # 100-200 ms/bit


@FITTS_FLOOR_NOT_YET
def test_fitts_1954_narrowest_width_is_met(fitts_result):
    from delayed_ilqr.experiments.fitts import FITTS_1954_WIDTHS, narrowest_width
    assert np.all(narrowest_width(fitts_result) <= min(FITTS_1954_WIDTHS)), narrowest_width(fitts_result)


@pytest.fixture(scope="module")
def growth_result():
    # the torque-driven arm with its human preset (the same experiment code; its four delay pairs
    # compile in a fraction of the six-muscle arm's time): the six-muscle arm's sweeps are the full
    # test below
    from delayed_ilqr.experiments.delay_growth import delay_growth_experiment
    return delay_growth_experiment("arm2", motor_delays=(0.0, 0.06), sensory_delays=(0.0, 0.08), targets=1,
                                   trials=60, seed=SEED)


def test_cost_error_and_scatter_grow_with_each_delay(growth_result):
    from delayed_ilqr.experiments.delay_growth import monotone
    for points in (growth_result.motor, growth_result.sensory):
        assert all(s.startswith("CONVERGED") for p in points for s in p.statuses)
        assert monotone([p.cost.mean for p in points])
        assert monotone([p.error_median for p in points])
        assert monotone([p.scatter for p in points])
        assert monotone([p.predicted_cost for p in points])     # the local (linearised) prediction too


# -- full size (make bench): the docs' numbers ----------------------------------------------------

@pytest.mark.full
@KICK_NOT_YET
def test_full_kick_ends_within_twice_the_unperturbed_error():
    from delayed_ilqr.experiments.kick import kick_experiment
    a = kick_experiment(ARM, trials=200, seed=SEED).analysis
    assert a.first_change == pytest.approx(a.loop_latency)
    assert a.error_ratio <= 2.0, (a.error_kicked.median, a.error_base.median)


@pytest.mark.full
def test_full_target_jumps():
    from delayed_ilqr.experiments.target_jump import target_jump_experiment
    r = target_jump_experiment(ARM, times_before_end=(0.1, 0.2, 0.3, 0.4), trials=100, seed=SEED)
    assert r.solver_failures == 0
    assert all(a.first_change == pytest.approx(a.loop_latency) for a in r.analyses)
    assert all(a.error_new.median < 0.01 for a in r.analyses if a.time_before_end >= 0.2)
    made = [a.corrected for a in r.analyses]
    assert all(x < y for x, y in zip(made, made[1:])) and max(made) <= 1.05


@pytest.mark.full
def test_full_bar_target_scatters_along_the_bar():
    from delayed_ilqr.experiments.minimal_intervention import minimal_intervention_experiment
    point, bar = minimal_intervention_experiment(ARM, trials=300, seed=SEED)
    assert bar.status.startswith("CONVERGED") and bar.ratio >= 1.5


@pytest.fixture(scope="module")
def full_fitts():
    from delayed_ilqr.experiments.fitts import fitts_experiment
    return fitts_experiment(ARM, trials=100, seed=SEED)                 # the command's default: the docs' numbers


@pytest.mark.full
def test_full_fitts_law_at_two_delays(full_fitts):
    model, late = full_fitts
    assert model.fit is not None and model.fit.r2 >= 0.9, model.fit
    both = np.isfinite(model.mt) & np.isfinite(late.mt) & (model.mt > model.movement_times[0])
    assert both.sum() >= 3 and np.all(late.mt[both] > model.mt[both])    # a longer delay, slower


@pytest.mark.full
@FITTS_SLOPE_NOT_YET
def test_full_fitts_slope_within_the_published_range(full_fitts):
    from delayed_ilqr.experiments.fitts import SLOPE_RANGE
    assert SLOPE_RANGE[0] <= full_fitts[0].fit.b <= SLOPE_RANGE[1], full_fitts[0].fit


@pytest.mark.full
def test_full_delay_growth():
    from delayed_ilqr.experiments.delay_growth import delay_growth_experiment, monotone
    r = delay_growth_experiment(ARM, trials=100, seed=SEED)
    for points in (r.motor, r.sensory):
        for values in ([p.cost.mean for p in points], [p.error_median for p in points],
                       [p.scatter for p in points], [p.predicted_cost for p in points]):
            assert monotone(values), values
