"""Statistics a reader can trust: every study table gives the Monte Carlo mean with its 95 % interval
and the median, labels ``expected_cost`` as the local (linearised) prediction, and warns when the
Monte Carlo mean departs from that prediction by more than 2x either way."""
import math
import types

import numpy as np
import pytest

from delayed_ilqr.experiments import tables
from delayed_ilqr.experiments.center_out import TargetResult
from delayed_ilqr.experiments.delay_study import ControllerResult
from delayed_ilqr.models import point_mass
from delayed_ilqr.statistics import PREDICTION_FACTOR, prediction_warning, sample_stats, summarize


@pytest.mark.parametrize("ratio", [3.0, 1 / 3.0, 341.0])
def test_a_monte_carlo_mean_beyond_twice_the_prediction_either_way_warns_in_one_line(ratio):
    line = prediction_warning("aware at 100 ms", 2.0 * ratio, 2.0)
    assert line is not None and "\n" not in line
    assert line.startswith("warning: aware at 100 ms") and "local (linearised) prediction" in line
    assert f"{ratio:.3g}x" in line


@pytest.mark.parametrize("ratio", [1.0, 1.5, 1 / 1.5, 1.999])
def test_a_monte_carlo_mean_within_twice_the_prediction_does_not_warn(ratio):
    assert PREDICTION_FACTOR == 2.0
    assert prediction_warning("aware", 5.0 * ratio, 5.0) is None


def test_no_prediction_no_warning_and_a_non_positive_prediction_warns():
    assert prediction_warning("ignorant", 3.0, None) is None
    assert prediction_warning("x", 3.0, 0.0) is not None
    assert prediction_warning("x", 3.0, -1.0) is not None
    with pytest.raises(ValueError, match="factor must be greater than 1"):
        prediction_warning("x", 1.0, 1.0, factor=0.5)


def _controller(costs, predicted, errors=None):
    """A ControllerResult of synthetic per-trial costs (no solve: the table reads only numbers)."""
    costs = np.asarray(costs, dtype=float)
    errors = np.abs(costs) * 1e-3 if errors is None else errors
    diverged = ~np.isfinite(costs)
    return ControllerResult(
        model="synthetic", delay=0.1, delay_steps=10, noise=True, controller="aware", converged=True,
        status="CONVERGED", message="", iterations=3, solve_time=0.01, first_solve_time=0.1, nominal_cost=1.0,
        predicted_cost=predicted, cost=sample_stats(costs, diverged), endpoint_error=sample_stats(errors, diverged),
        divergence_bound=math.inf, endpoint_label="hand position error", endpoint_unit="m",
        summary=summarize(costs, np.zeros((costs.size, 2))), n_trials=costs.size, seed=0, substeps=1,
        problem=point_mass(delay=0.1), solution=None, runs=None)


def test_the_delay_study_table_has_the_mean_with_its_interval_and_the_median_of_the_trials():
    rng = np.random.default_rng(3)
    costs = rng.lognormal(0.0, 1.0, 101)
    header, rows = tables.delay_study_rows([_controller(costs, predicted=1.0)])
    row = dict(zip(header, rows[0]))
    st = sample_stats(costs)
    assert row[tables.PREDICTED] == tables.num(1.0)
    mean_col = next(h for h in header if h.startswith("MC mean J"))
    assert mean_col == "MC mean J [95% CI]"
    assert row[mean_col] == f"{tables.num(np.mean(costs))} [{tables.num(st.ci95[0])}, {tables.num(st.ci95[1])}]"
    assert st.ci95[0] < np.mean(costs) < st.ci95[1]
    assert row["MC median J [IQR]"].split(" ")[0] == tables.num(np.median(costs))


def test_the_delay_study_warns_at_3x_and_not_at_1_5x():
    costs = np.full(50, 1.0) + np.linspace(-0.1, 0.1, 50)      # mean 1.0
    assert tables.delay_study_warnings([_controller(costs, predicted=1 / 1.5)]) == []
    assert tables.delay_study_warnings([_controller(costs, predicted=1.5)]) == []
    (line,) = tables.delay_study_warnings([_controller(costs, predicted=1 / 3)])
    assert "synthetic, aware at 100 ms" in line and "3x" in line
    (line,) = tables.delay_study_warnings([_controller(costs, predicted=3.0)])
    assert "0.333x" in line


def _target(costs, predicted):
    costs = np.asarray(costs, dtype=float)
    n = costs.size
    ends = np.stack([np.linspace(0, 1e-3, n), np.linspace(0, 2e-3, n) ** 2], axis=1)
    return TargetResult(target=np.zeros(2), status="CONVERGED_COST", iterations=5, cost=1.0, predicted_cost=predicted,
                        hand_error=0.0, hand_speed=0.0, endpoints=ends, mc_error=np.linalg.norm(ends, axis=1),
                        mc_cost=costs, diverged=np.zeros(n, bool))


def test_the_center_out_table_pools_the_trials_and_its_median_is_the_median_of_all_trials():
    rng = np.random.default_rng(0)
    a, b = rng.lognormal(0, 1, 40), rng.lognormal(1, 1, 40)
    result = types.SimpleNamespace(delay=0.05, design="noise-aware", solve_time=0.2,
                                   targets=[_target(a, 1.0), _target(b, 2.0)])
    header, (row,) = tables.center_out_rows([result])
    row = dict(zip(header, row))
    both = np.concatenate([a, b])
    assert row["MC median J (all trials)"] == tables.num(np.median(both), 3)
    assert row["MC mean J [95% CI] (all trials)"].startswith(tables.num(np.mean(both), 3) + " [")
    assert row[f"{tables.PREDICTED} (mean over targets)"] == f"{1.5:.3g}"


def test_center_out_warns_once_per_design_naming_the_targets_that_depart():
    near = np.full(30, 1.0)
    result = types.SimpleNamespace(delay=0.1, design="noise-aware", solve_time=0.2,
                                   targets=[_target(near, 1 / 1.5), _target(near * 3, 1.0), _target(near, 1.0)])
    (line,) = tables.center_out_warnings([result])
    assert "targets 2 of 3" in line and "3x" in line
    result.targets = [_target(near, 1.5), _target(near, 1 / 1.5)]
    assert tables.center_out_warnings([result]) == []


def test_sweep_rows_report_the_mean_interval_and_median_and_the_sweep_warns():
    xr = pytest.importorskip("xarray")
    dims = ("delay", "seed")
    ds = xr.Dataset(dict(
        status=(("delay",), np.array([0, 0])), iterations=(("delay",), np.array([4, 5])),
        expected_cost=(("delay",), np.array([1.0, 1.0])),
        mc_cost_mean=(dims, np.array([[1.2], [3.5]])), mc_cost_ci_low=(dims, np.array([[1.1], [3.0]])),
        mc_cost_ci_high=(dims, np.array([[1.3], [4.0]])), mc_cost_median=(dims, np.array([[1.15], [2.9]])),
        mc_diverged=(dims, np.array([[0], [1]])),
        mc_endpoint_error_median=(dims, np.array([[0.001], [0.002]]), {"units": "m"})),
        coords=dict(delay=[0.0, 0.1]), attrs=dict(trials=10))
    header, rows = tables.sweep_rows(ds)
    col = dict(zip(header, rows[1]))
    assert col["MC mean J [95% CI]"] == "3.5 [3, 4]" and col["MC median J"] == "2.9"
    assert col[tables.PREDICTED] == "1"
    (line,) = tables.sweep_warnings(ds)
    assert "1 of 2 cells" in line and "3.5x" in line
