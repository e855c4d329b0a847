"""The ``sweep`` command: solve and simulate a model on every cell of a grid over its factory's
arguments, into a resumable store ([`delayed_ilqr.sweeps`][delayed_ilqr.sweeps])."""
from __future__ import annotations

import importlib.util
import json
import shutil
import sys
import time

import click
import jax

from .._files import save_figure, write_text
from ..experiments import designs, report, tables
from ..models import REGISTRY
from .arguments import DelayFrame, GridAxis, IntList, ModelType, Setting
from .output import manifest, out_option

SWEEP_STORE, SWEEP_FIGURE = "store", "sweep.png"


class MissingExtra(click.ClickException):
    """A package of the ``sweep`` extra is not installed (exit code 3: not a usage error)."""

    exit_code = 3

    def format_message(self) -> str:
        return self.message


def _remove_if_empty(folder) -> None:
    """Removes ``folder``, made by this command, when no file was written in it."""
    if folder is not None and folder.is_dir() and not any(p.is_file() for p in folder.rglob("*")):
        shutil.rmtree(folder, ignore_errors=True)


def _require_extra(modules: list[str]) -> None:
    """The sweep extra's packages importable, else `MissingExtra` with the install command."""
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise MissingExtra(f"delayed-ilqr sweep needs the sweep extra (xarray, zarr, dask[distributed]); not installed: "
                           f"{', '.join(missing)}. Install it with: pip install 'delayed-ilqr[sweep]'")


@click.command("sweep")
@click.argument("model", type=ModelType(), metavar="MODEL")
@click.option("--grid", "axes", type=GridAxis(), multiple=True, required=True,
              help="A grid dimension over an argument of the model's factory, repeatable: NAME=a,b,c, "
                   "NAME=start:stop:step (inclusive) or NAME=[..];[..] for vectors, e.g. --grid delay=0:0.15:0.01 "
                   "--grid sigma_u=0.01,0.02.")
@click.option("--set", "settings_", type=Setting(), multiple=True,
              help="A factory argument held fixed, repeatable: NAME=VALUE, e.g. --set sigma_u=0.01.")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="The stochastic plant or the deterministic one (the factory's noise argument).")
@click.option("--seeds", type=IntList(), default="0", show_default=True,
              help="Comma-separated Monte Carlo seeds (the Dataset's seed dimension).")
@click.option("--trials", type=click.IntRange(min=1), default=100, show_default=True,
              help="Monte Carlo trials per cell and seed.")
@click.option("--design", type=click.Choice(sorted(designs.REGISTRY)), default="aware", show_default=True,
              help="The controller design (experiments.designs): aware is Theorem 1 on the plant.")
@click.option("--batch-size", type=click.IntRange(min=1), default=16, show_default=True,
              help="At most this many cells of equal structure per vmapped solve.")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="Run on a dask.distributed LocalCluster of this many worker processes (0: in this process).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on the Dask cluster of this scheduler, e.g. tcp://host:8786 (docs/sweeps.md).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="A progress bar over the cells.")
@click.option("--delay-frame", type=DelayFrame(), default="auto", show_default=True,
              help="auto: the delay is data, in a frame of the grid's longest delay, so all delays share one "
                   "compiled solver (results equal to round-off; each solve costs one at the longest delay), "
                   "when no delay has more than 1000 cells and the model has no delayed sensors; none: one solver per delay; N: a frame of N steps "
                   "(docs/sweeps.md).")
@out_option(required=True, help="Folder of the sweep: store/ (results.zarr and completion markers; a second "
                                 "run of the same command resumes it), sweep.png, manifest.json.")
def sweep_command(model, axes, settings_, noise, seeds, trials, design, batch_size, workers, scheduler, progress,
                  delay_frame, out, overwrite):
    """Solve and simulate MODEL on every cell of a grid over its factory's arguments.

    Each cell is solved (cells of equal structure together, one vmap), run --trials times per seed,
    and its statistics written to --out/store as soon as its batch is done: an interrupted sweep
    resumes where it stopped when the same command runs again, and finished cells are not
    computed twice. Prints a summary table and draws --out/sweep.png against the first --grid
    dimension. Exits 1 when some cell did not converge.
    """
    _require_extra(["xarray", "zarr"] + (["distributed"] if workers or scheduler else []))
    from .. import plot
    from ..sweeps import sweep
    grid = dict(axes)
    if len(grid) != len(axes):
        raise click.BadParameter("names a dimension twice", param_hint="'--grid'")
    fixed = dict(settings_)
    if "noise" not in grid and "noise" not in fixed:
        fixed["noise"] = noise
    if workers and scheduler:
        raise click.BadParameter("give either --workers (a LocalCluster) or --scheduler (a running cluster)",
                                 param_hint="'--workers'")
    executor = scheduler if scheduler else ("local" if workers else None)
    store = out / SWEEP_STORE
    if out.is_dir() and any(out.iterdir()) and not (store / "sweep.json").is_file() and not overwrite:
        raise click.BadParameter(f"{out} is not empty and holds no sweep; pass --overwrite to replace it whole",
                                 param_hint="'--out'")
    if overwrite and out.is_dir() and not (store / "sweep.json").is_file():
        shutil.rmtree(out)
    created = next((p for p in reversed([out, *out.parents]) if not p.exists()), None)   # the top folder made here
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise click.BadParameter(f"cannot create {out}: {exc.strerror or exc}", param_hint="'--out'") from None
    start = time.perf_counter()
    try:
        # a built-in model by name (what the store records); a user's factory as the function
        ds = sweep(model.name if model.name in REGISTRY else model.factory, grid, seeds, trials, fixed=fixed,
                   design=design, store=store, overwrite=overwrite,
                   scheduler=executor, n_workers=max(workers, 1), batch_size=batch_size, progress=progress,
                   # a LocalCluster's workers share this process's cache; a remote cluster's use their own
                   cache_dir=None if scheduler else jax.config.jax_compilation_cache_dir,
                   cache=jax.config.jax_compilation_cache_dir is not None,
                   delay_frame=None if delay_frame == "none" else delay_frame)
    except (ValueError, TypeError) as exc:
        _remove_if_empty(created)             # a refused sweep leaves no folder it made
        raise click.UsageError(str(exc)) from None
    except BaseException:
        _remove_if_empty(created)
        raise
    elapsed = time.perf_counter() - start
    click.echo(tables.text_table(tables.sweep_rows(ds)))
    for line in tables.sweep_warnings(ds):
        click.echo(line, err=True)
    figure = plot.plot_sweep(ds)
    save_figure(figure, out / SWEEP_FIGURE, dpi=report.DPI)
    files = sorted(str(f.relative_to(out)) for f in out.rglob("*") if f.is_file() and f.name != "manifest.json")
    settings = dict(model=model.name, grid={k: [list(v) if isinstance(v, tuple) else v for v in vs]
                                            for k, vs in grid.items()},
                    fixed=fixed, seeds=seeds, trials=trials, design=design, batch_size=batch_size,
                    elapsed_seconds=elapsed)
    write_text(out / "manifest.json", json.dumps(manifest(settings, len(files)), indent=2, default=repr) + "\n")
    n_failed = int((ds.converged.values != 1).sum())
    click.echo(f"wrote {SWEEP_STORE}/, {SWEEP_FIGURE}, manifest.json to {out} ({elapsed:.1f} s)")
    if n_failed:
        click.echo(f"warning: {n_failed} of {ds.converged.size} cells did not converge (status in the Dataset)",
                   err=True)
        sys.exit(1)
