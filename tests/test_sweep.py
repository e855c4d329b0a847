"""``delayed_ilqr.sweep``: each cell equals the library's own solve and Monte Carlo, an interrupted
or damaged store resumes to the same numbers, and a 2-worker Dask LocalCluster (also with a
worker killed mid-sweep) gives the results of the local run, every cell once.

Small problems (the noisy point mass, K = 20, 20 trials) keep it within a minute or so; the Dask
workers share a temporary persistent compilation cache with this process, so they mostly read
the solvers compiled here instead of compiling them again.
"""
import json
import os
import sys

import jax
import numpy as np
import pytest

xr = pytest.importorskip("xarray")
pytest.importorskip("zarr")
distributed = pytest.importorskip("distributed")

import delayed_ilqr as di                                      # noqa: E402
from delayed_ilqr import statistics                            # noqa: E402
from delayed_ilqr.experiments.engine import endpoint_error     # noqa: E402
from delayed_ilqr.models import point_mass                     # noqa: E402
from delayed_ilqr.sweeps import compute, run   # noqa: E402

K = 20
TARGETS = [(0.2, 0.1, 0.0, 0.0), (0.1, 0.2, 0.0, 0.0), (0.0, 0.15, 0.0, 0.0)]
GRID = {"delay": [0.0, 0.03], "x_target": TARGETS}
ARGS = dict(seeds=[0, 3], trials=20, fixed={"noise": True, "horizon": K}, batch_size=4, progress=False)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    """A persistent compilation cache for this module (this process and the Dask workers); JAX's
    setting is restored afterwards."""
    from jax.experimental.compilation_cache import compilation_cache as cc
    before = jax.config.jax_compilation_cache_dir
    folder = di.enable_compilation_cache(tmp_path_factory.mktemp("jax-cache"))
    yield folder
    cc.reset_cache()
    jax.config.update("jax_compilation_cache_dir", before)


@pytest.fixture(scope="module")
def reference(cache_dir):
    """The sweep computed here, in memory."""
    return di.sweep("point_mass", GRID, **ARGS)


def test_every_cell_is_the_librarys_own_solve_and_monte_carlo(reference):
    """Each cell equals a plain ``solve`` of its problem (not the sweep's vmap), ``simulate`` per seed
    and ``statistics.sample_stats``. On CPU bitwise: the batching rule runs each problem through
    the same compiled solver body (``ilqg/batching.py``); elsewhere to round-off."""
    rtol = 0.0 if jax.default_backend() == "cpu" else 1e-10
    ds = reference
    assert dict(ds.sizes) == {"delay": 2, "x_target": 3, "seed": 2, "x_target_component": 4}
    assert ds.delay.attrs["units"] == "s" and ds.mc_endpoint_error_mean.attrs["units"] == "m"
    np.testing.assert_array_equal(ds.x_target_value.values, np.asarray(TARGETS))
    for i, delay in [(1, 0.03)]:                   # one delay: each plain solve compiles for its delay
        for j, target in enumerate(TARGETS):
            problem = point_mass(delay=delay, x_target=target, noise=True, horizon=K)
            sol = di.solve(problem)
            cell = ds.isel(delay=i, x_target=j)
            assert int(cell.status) == int(sol.status) and int(cell.iterations) == int(sol.iterations)
            np.testing.assert_allclose([float(cell.cost), float(cell.expected_cost), float(cell.endpoint_error)],
                                       [float(sol.cost), float(sol.expected_cost),
                                        endpoint_error(problem, np.asarray(sol.x)[-1:])[0]], rtol=rtol)
            bound = statistics.divergence_bound(problem)
            for k, seed in enumerate(ARGS["seeds"]):
                runs = di.simulate(problem, sol.policy, ARGS["trials"], seed=seed)
                diverged = statistics.diverged_trials(runs.cost, bound)
                stats = statistics.sample_stats(runs.cost, diverged)
                errors = statistics.sample_stats(endpoint_error(problem, np.asarray(runs.x)[:, -1]), diverged)
                got = cell.isel(seed=k)
                assert int(got.mc_diverged) == stats.n_diverged
                np.testing.assert_allclose([float(got.mc_cost_mean), float(got.mc_cost_median),
                                            float(got.mc_cost_ci_low), float(got.mc_cost_ci_high),
                                            float(got.mc_endpoint_error_mean), float(got.mc_endpoint_error_median)],
                                           [stats.mean, stats.median, *stats.ci95, errors.mean, errors.median],
                                           rtol=rtol)
    # seeds differ: the Monte Carlo is not one sample repeated
    assert not np.array_equal(ds.mc_cost_mean.isel(seed=0).values, ds.mc_cost_mean.isel(seed=1).values)


def test_cells_are_grouped_by_structure_and_cut_into_padded_batches():
    """Targets and noise levels are data (sigma_u is a leaf of the arm's noise: one
    compiled solver for all), delays are static (one each); batches are padded to a power of two,
    never beyond batch_size."""
    from delayed_ilqr.models import arm2
    from delayed_ilqr.sweeps.grid import batches, cells, check_grid, padded_size
    grid = check_grid({"delay": [0.0, 0.03], "sigma_u": [0.01, 0.02],
                       "x_target": [(1.5 + 0.01 * i, 1.0, 0.0, 0.0) for i in range(7)]})
    plan = batches(cells(grid), lambda c: arm2(noise=True, **c.kwargs), batch_size=4)
    # 2 structures (delays) x 14 cells (2 noise levels x 7 targets)
    assert [(len(b.cells), b.size) for b in plan] == [(4, 4), (4, 4), (4, 4), (2, 2)] * 2
    for b in plan:
        assert len({c.kwargs["delay"] for c in b.cells}) == 1
    assert sorted(c.index for b in plan for c in b.cells) == [c.index for c in cells(grid)]
    assert [padded_size(n, 16) for n in (1, 2, 3, 5, 9, 16)] == [1, 2, 4, 8, 16, 16]


def test_a_delay_frame_puts_every_delay_in_one_batch_with_the_unframed_results(reference, monkeypatch):
    """``delay_frame="auto"``: the two delays of the grid (0 and 30 ms, l = 0 and 3) share one
    structure, so the six cells are one batch of one compiled solver, and every value equals the
    unframed sweep's (the module's reference) to round-off (docs/derivation.md §17)."""
    plans = []
    real = run.batches

    def recorded(*args, **kwargs):
        plans.append(real(*args, **kwargs))
        return plans[-1]

    monkeypatch.setattr(run, "batches", recorded)
    ds = di.sweep("point_mass", GRID, delay_frame="auto", **dict(ARGS, batch_size=8))
    assert [(len(b.cells), b.size) for b in plans[0]] == [(6, 8)]
    assert ds.attrs["delay_frame"] == 3 and reference.attrs["delay_frame"] == -1
    for name in ("status", "iterations", "mc_diverged"):
        np.testing.assert_array_equal(ds[name].values, reference[name].values)
    for name in ("cost", "expected_cost", "endpoint_error", "mc_cost_mean", "mc_cost_median",
                 "mc_endpoint_error_mean"):
        np.testing.assert_allclose(ds[name].values, reference[name].values, rtol=1e-9)
    with pytest.raises(ValueError, match="delay_frame must be at least delay_steps"):
        di.sweep("point_mass", GRID, delay_frame=2, **ARGS)


def test_the_sweep_figure_draws_the_datasets_values_in_mm(reference):
    """plot_sweep: one line per target; the cost panel is the seed-mean of mc_cost_mean, the error
    panel the seed-mean median endpoint error in mm (the Dataset's unit is m), labelled so."""
    from delayed_ilqr.plot import plot_sweep
    fig = plot_sweep(reference)
    cost_ax, error_ax = fig.axes
    assert "[mm]" in error_ax.get_ylabel() and error_ax.get_xlabel() == "delay [ms]"
    for j, (cost_line, error_line) in enumerate(zip(cost_ax.get_lines(), error_ax.get_lines())):
        cell = reference.isel(x_target=j)
        np.testing.assert_allclose(cost_line.get_ydata(), cell.mc_cost_mean.mean("seed").values)
        np.testing.assert_allclose(error_line.get_ydata(), 1e3 * cell.mc_endpoint_error_median.mean("seed").values)
    assert len(error_ax.get_lines()) == len(TARGETS)


def test_auto_frames_only_where_it_pays():
    """"auto" frames a grid of several delays with at most AUTO_FRAME_MAX_CELLS cells each; one
    delay, or more cells per delay, keep a solver per delay; an int frames whatever the grid."""
    settings = compute.Settings(point_mass, (), "aware", None, (0,), 10, 1)
    short, longer = point_mass(delay=0.0), point_mass(delay=0.03)
    few = {(i,): (short if i % 2 else longer) for i in range(10)}
    many = {(i,): (short if i % 2 else longer) for i in range(2 * run.AUTO_FRAME_MAX_CELLS + 2)}
    framed, problems = run._framed(settings, few, "auto")
    assert framed.delay_frame == 3 and {p.delay_frame for p in problems.values()} == {3}
    assert run._framed(settings, many, "auto")[0].delay_frame is None
    assert run._framed(settings, {(0,): short}, "auto")[0].delay_frame is None
    assert run._framed(settings, many, 5)[0].delay_frame == 5


class Interrupted(Exception):
    pass


def test_an_interrupted_sweep_resumes_computing_only_what_is_missing_with_identical_results(
        reference, tmp_path, monkeypatch):
    path = tmp_path / "store"
    real = compute.compute_batch
    computed = []

    def interrupt_after_one(settings, batch, plants=None):
        if len(computed) == 1:
            raise Interrupted
        computed.append(batch.number)
        return real(settings, batch, plants)

    monkeypatch.setattr(run, "compute_batch", interrupt_after_one)
    with pytest.raises(Interrupted):
        di.sweep("point_mass", GRID, store=path, **ARGS)
    partial = di.open_sweep(path)
    # batches (same delay together, at most 4): [(0,0), (0,1), (0,2)], [(1,0), (1,1), (1,2)]
    assert int(partial.finished.sum()) == 3 and np.isnan(partial.cost.values[partial.finished.values == 0]).all()

    computed.clear()
    monkeypatch.setattr(run, "compute_batch", lambda s, b, p=None: (computed.append(b.number), real(s, b, p))[1])
    resumed = di.sweep("point_mass", GRID, store=path, **ARGS)
    assert computed == [1]                      # only the batch that had not been written
    xr.testing.assert_identical(resumed, reference)
    computed.clear()
    again = di.sweep("point_mass", GRID, store=path, **ARGS)    # a re-run computes nothing
    assert computed == [] and int(di.open_sweep(path).finished.sum()) == 6
    xr.testing.assert_identical(again, reference)


def test_a_damaged_store_is_detected_and_its_cells_computed_again(reference, tmp_path, monkeypatch):
    path = tmp_path / "store"
    di.sweep("point_mass", GRID, store=path, **ARGS)
    real, computed = compute.compute_batch, []
    monkeypatch.setattr(run, "compute_batch", lambda s, b, p=None: (computed.append(b.number), real(s, b, p))[1])
    # a write interrupted between the data and the marker: batch 0's (delay 0) marker is gone
    (path / "cells" / "batch-0.json").unlink()
    # a value changed after its marker was written (a checksum mismatch): cell (1, 2)'s iterations
    import zarr
    zarr.open_group(path / "results.zarr", mode="r+")["iterations"][1, 2] = 99
    np.testing.assert_array_equal(di.open_sweep(path).finished.values, [[0, 0, 0], [1, 1, 0]])
    repaired = di.sweep("point_mass", GRID, store=path, **ARGS)
    assert computed == [0, 1]             # batch 1 again for cell (1, 2); its other cells are kept
    xr.testing.assert_identical(repaired, reference)
    # a damaged chunk (row 1 of the costs: 3 cells in one chunk) cannot be decoded: its cells again
    (path / "results.zarr" / "cost" / "c" / "1" / "0").write_bytes(b"\x00garbage")
    np.testing.assert_array_equal(di.open_sweep(path).finished.values, [[1, 1, 1], [0, 0, 0]])
    computed.clear()
    repaired = di.sweep("point_mass", GRID, store=path, **ARGS)
    assert computed == [1]
    xr.testing.assert_identical(repaired, reference)
    markers = [json.loads(p.read_text())["cells"] for p in sorted((path / "cells").glob("batch-*.json"))]
    keys = [k for m in markers for k in m]
    assert sorted(keys) == sorted(f"{i},{j}" for i in range(2) for j in range(3))   # each cell once


@pytest.mark.parametrize("damage", [b"", b"\x00garbage", "truncated"])
def test_a_damaged_per_seed_chunk_is_computed_again(reference, tmp_path, monkeypatch, damage):
    """A chunk of a per-seed variable (mc_*: its cells' values for every seed) emptied, truncated or
    overwritten: a resume computes that chunk's cells again and rewrites the whole chunk, seed axis
    included, with the reference's numbers."""
    path = tmp_path / "store"
    di.sweep("point_mass", GRID, store=path, **ARGS)
    chunk = path / "results.zarr" / "mc_cost_mean" / "c" / "1" / "0" / "0"
    data = chunk.read_bytes()
    chunk.write_bytes(data[: len(data) // 2] if damage == "truncated" else damage)
    np.testing.assert_array_equal(di.open_sweep(path).finished.values, [[1, 1, 1], [0, 0, 0]])
    real, computed = compute.compute_batch, []
    monkeypatch.setattr(run, "compute_batch", lambda s, b, p=None: (computed.append(b.number), real(s, b, p))[1])
    repaired = di.sweep("point_mass", GRID, store=path, **ARGS)
    assert computed == [1]
    xr.testing.assert_identical(repaired, reference)
    assert int(di.open_sweep(path).finished.sum()) == 6


def test_a_damaged_store_file_is_one_error_naming_the_store_and_file(reference, tmp_path):
    path = tmp_path / "store"
    di.sweep("point_mass", GRID, store=path, **ARGS)
    meta = path / "results.zarr" / "zarr.json"
    meta.write_text("{not json")
    for call in (lambda: di.sweep("point_mass", GRID, store=path, **ARGS), lambda: di.open_sweep(path)):
        with pytest.raises(ValueError, match=rf"{meta}: .*not valid JSON.*--overwrite") as info:
            call()
        assert "sweep store" in str(info.value)
    variable = path / "results.zarr" / "cost" / "zarr.json"
    meta.unlink()
    with pytest.raises(ValueError, match=rf"{path / 'results.zarr'}.*sweep store"):
        di.open_sweep(path)
    (path / "sweep.json").write_text("\xff")
    with pytest.raises(ValueError, match=rf"{path / 'sweep.json'}"):
        di.sweep("point_mass", GRID, store=path, **ARGS)
    assert variable.exists()


def test_a_store_of_another_sweep_is_refused_unless_overwrite(reference, tmp_path):
    path = tmp_path / "store"
    first = {"delay": [0.0], "x_target": TARGETS}            # shapes compiled for the reference
    di.sweep("point_mass", first, store=path, **ARGS)
    with pytest.raises(ValueError, match="holds another sweep"):
        di.sweep("point_mass", {"delay": [0.03], "x_target": TARGETS}, store=path, **ARGS)
    with pytest.raises(ValueError, match="holds another sweep"):
        di.sweep("point_mass", first, store=path, **dict(ARGS, trials=21))
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="is not a sweep store"):
        di.sweep("point_mass", first, store=tmp_path / "plain", **ARGS)
    ds = di.sweep("point_mass", {"delay": [0.03], "x_target": TARGETS}, store=path, overwrite=True, **ARGS)
    xr.testing.assert_identical(ds.drop_attrs(), reference.isel(delay=[1]).drop_attrs())


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(grid={"seed": [0]}), ValueError, "not 'seed'"),
    (dict(grid={"delay": []}), ValueError, r"grid\['delay'\] must hold at least one value"),
    (dict(grid={"delay": [0.0, 0.0]}), ValueError, "must not repeat"),
    (dict(grid={"delay": [0.0, 0.025]}), ValueError, r"grid cell \{'delay': 0.025\}: delay must be a whole number"),
    (dict(grid={"delay": [0.0]}, fixed={"delay": 0.0}), ValueError, "fixed and grid must not name"),
    (dict(grid={"delay": [0.0]}, seeds=[1, 1]), ValueError, "no seed twice"),
    (dict(grid={"delay": [0.0]}, trials=0), ValueError, "trials"),
    (dict(grid={"delay": [0.0]}, design="clever"), ValueError, "design must be one of"),
])
def test_bad_arguments_name_the_argument(kwargs, error, match):
    args = dict(seeds=[0], trials=5, progress=False) | kwargs
    grid = args.pop("grid")
    with pytest.raises(error, match=match):
        di.sweep("point_mass", grid, **args)


def test_the_sweep_command_with_sensors_runs_with_the_default_delay_frame(cache_dir, tmp_path):
    """--delay-frame auto (the default) frames delays only where a frame is available: with delayed
    sensors every delay keeps its own solver, and the results are the unframed sweep's."""
    from click.testing import CliRunner
    from delayed_ilqr import cli
    out = tmp_path / "out"
    result = CliRunner().invoke(cli.main, [
        "sweep", "point_mass", "--grid", "delay=0,0.03", "--set", "sensory_delay=0.02", "--set", f"horizon={K}",
        "--trials", "4", "--no-progress", "--out", str(out)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    unframed = di.sweep("point_mass", {"delay": [0.0, 0.03]}, [0], 4, progress=False, delay_frame=None,
                        fixed={"sensory_delay": 0.02, "horizon": K, "noise": True})
    xr.testing.assert_identical(di.open_sweep(out / "store").drop_vars("finished").drop_attrs(),
                                unframed.drop_attrs())


def test_repeated_cells_and_trials_that_cannot_fit_are_refused_before_solving(monkeypatch):
    """delay=[0, 0.0] or two delays of one step count are one cell twice; trials beyond memory are
    refused with the count given, before any batch is computed."""
    monkeypatch.setattr(run, "compute_batch", lambda *a, **k: pytest.fail("computed before refusing"))
    args = dict(seeds=[0], trials=5, progress=False, fixed={"horizon": K})
    with pytest.raises(ValueError, match=r"grid\['delay'\] must not repeat a value; got 0 and 0.0"):
        di.sweep("point_mass", {"delay": [0, 0.0]}, **args)
    with pytest.raises(ValueError, match=r"grid\['delay'\]: 0.03 and 0.030000000001 are the same delay, 3 steps"):
        di.sweep("point_mass", {"delay": [0.03, 0.030000000001]}, **args)
    with pytest.raises(ValueError, match=r"trials=1000000000000 trials in each of 2 runs"):
        di.sweep("point_mass", {"delay": [0.0, 0.03]}, **dict(args, trials=10 ** 12, delay_frame=3))


def test_a_refused_sweep_leaves_no_out_folder(tmp_path):
    from click.testing import CliRunner
    from delayed_ilqr import cli
    for args in (["--grid", "delay=0.025"], ["--grid", "delay=0,0.0"], ["--grid", "delay=0", "--trials", str(10 ** 12)]):
        out = tmp_path / "new" / "out"
        result = CliRunner().invoke(cli.main, ["sweep", "point_mass", *args, "--out", str(out)])
        assert result.exit_code == 2, result.output
        assert list(tmp_path.iterdir()) == [], result.output


# -- Dask ------------------------------------------------------------------------------------------

def dying_point_mass(flag, **kwargs):
    """point_mass, except that the first call inside a Dask worker kills that worker's process."""
    try:
        distributed.get_worker()
    except ValueError:
        return point_mass(**kwargs)                       # not on a worker: the sweep's own checks
    try:
        os.close(os.open(flag, os.O_CREAT | os.O_EXCL))    # once over all workers
    except FileExistsError:
        return point_mass(**kwargs)
    os._exit(1)


@pytest.fixture(scope="module")
def client(cache_dir):
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])      # the workers cannot import tests/
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


def test_a_two_worker_local_cluster_gives_the_local_results_also_when_a_worker_dies(reference, client, cache_dir,
                                                                                    tmp_path):
    """Two LocalCluster workers; the first batch to start kills its worker (os._exit) when it
    builds its problems. The scheduler runs that batch again, and the sweep completes with the
    local run's numbers, every cell written once."""
    flag, path = tmp_path / "died", tmp_path / "store"
    args = dict(ARGS, fixed=dict(ARGS["fixed"], flag=str(flag)))
    ds = di.sweep(dying_point_mass, GRID, store=path, scheduler=client, cache_dir=cache_dir, **args)
    assert flag.exists()                                  # a worker did die
    assert len(client.scheduler_info()["workers"]) == 2    # and its nanny started a new one
    xr.testing.assert_identical(ds.drop_attrs(), reference.drop_attrs())    # attrs: the factory's name
    markers = [json.loads(p.read_text())["cells"] for p in sorted((path / "cells").glob("batch-*.json"))]
    keys = [k for m in markers for k in m]
    assert len(keys) == 6 and len(set(keys)) == 6
    assert int(di.open_sweep(path).finished.sum()) == 6


# -- the command line ------------------------------------------------------------------------------

def test_the_sweep_command_writes_the_store_and_figure_resumes_and_refuses_bad_arguments(reference, tmp_path):
    from click.testing import CliRunner
    from delayed_ilqr import cli
    out = tmp_path / "out"
    targets = ";".join(json.dumps(list(t)) for t in TARGETS)
    args = ["sweep", "point_mass", "--grid", "delay=0:0.03:0.03", "--grid", f"x_target={targets}", "--set",
            f"horizon={K}", "--seeds", "0,3", "--trials", "20", "--batch-size", "4", "--no-progress",
            "--delay-frame", "none", "--out", out]

    def invoke(*a):
        return CliRunner().invoke(cli.main, [str(x) for x in a], catch_exceptions=False)

    result = invoke(*args)
    assert result.exit_code == 0, result.output
    assert "CONVERGED" in result.output and (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["settings"]["grid"]["delay"] == [0.0, 0.03] and manifest["settings"]["fixed"]["noise"] is True
    xr.testing.assert_identical(di.open_sweep(out / "store").drop_vars("finished"), reference)
    again = invoke(*args)                                   # the same command: resumed, nothing to compute
    assert again.exit_code == 0 and "CONVERGED" in again.output
    other = invoke(*args[:-2], "--trials", "21", "--out", out)
    assert other.exit_code == 2 and "holds another sweep" in other.output
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    refused = invoke(*args[:-1], tmp_path / "mine")
    assert refused.exit_code == 2 and "holds no sweep" in refused.output
    bad = invoke("sweep", "point_mass", "--grid", "delay0.1", "--out", tmp_path / "bad")
    assert bad.exit_code == 2 and "NAME=VALUES" in bad.output
    refused_delay = invoke("sweep", "point_mass", "--grid", "delay=0.025", "--out", tmp_path / "bad")
    assert refused_delay.exit_code == 2 and "whole number of steps" in refused_delay.output
    small = invoke("sweep", "point_mass", "--grid", "delay=0:0.03:0.03", "--delay-frame", "2", "--out", tmp_path / "bad")
    assert small.exit_code == 2 and "delay_frame must be at least delay_steps" in small.output
    word = invoke("sweep", "point_mass", "--grid", "delay=0.03", "--delay-frame", "some", "--out", tmp_path / "bad")
    assert word.exit_code == 2 and "must be auto, none or" in word.output


def channel_point_mass(delay, **kwargs):
    """The point mass with its second channel ``delay`` late and its first half as late (per-channel
    delays, docs/derivation.md §18): a factory importable by name."""
    problem = point_mass(delay=delay, **kwargs)
    return problem.replace(delay_steps=[problem.delay_steps // 2, problem.delay_steps])


def test_per_channel_delays_are_framed_at_the_longest_channel_delay():
    """Per-channel delays ([0, 0], [1, 3]) in the sweep's frame rule: "auto" frames cells of
    different channel delays at the longest, one delay per channel repeated is one cell twice."""
    from delayed_ilqr.problem import shared_delay_frame
    settings = compute.Settings(channel_point_mass, (), "aware", None, (0,), 10, 1)
    cells = {(0,): channel_point_mass(0.0), (1,): channel_point_mass(0.03)}
    assert shared_delay_frame(cells.values()) == 3
    framed, problems = run._framed(settings, cells, "auto")
    assert framed.delay_frame == 3 and {p.delay_frame for p in problems.values()} == {3}
    assert shared_delay_frame([channel_point_mass(0.03)] * 2) is None


@pytest.mark.full
def test_per_channel_delays_share_one_frame_with_each_cells_own_solve():
    """A factory of per-channel delays ([0, 0] and [1, 3]): "auto" frames them at the longest
    channel delay, and the cell [1, 3] equals a plain solve of its problem (the suite keeps the
    frame rule, above)."""
    ds = di.sweep(channel_point_mass, {"delay": [0.0, 0.03]}, seeds=[0], trials=4,
                  fixed={"noise": True, "horizon": K}, progress=False, delay_frame="auto")
    assert ds.attrs["delay_frame"] == 3
    sol = di.solve(channel_point_mass(0.03, noise=True, horizon=K))
    cell = ds.isel(delay=1, seed=0)
    assert int(cell.status) == int(sol.status)
    np.testing.assert_allclose([float(cell.cost), float(cell.expected_cost)],
                               [float(sol.cost), float(sol.expected_cost)], rtol=1e-9)
