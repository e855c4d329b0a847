"""The command line's outputs: the ``--out`` folder written atomically with its ``manifest.json``,
the settings recorded in it, and the warning of a solve that did not converge."""
from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import pathlib
import shutil
import sys
from typing import Optional

import click

from .._files import write_text
from ..experiments.delay_text import delay_text
from . import interrupts

OUT_TYPE = click.Path(file_okay=False, dir_okay=True, writable=True, path_type=pathlib.Path)


def manifest(settings: dict, files) -> dict:
    """What ``manifest.json`` records: the command line, the package version, the time (UTC), the
    settings and ``files`` (the files written, as the command counts them)."""
    return dict(command=["delayed-ilqr"] + sys.argv[1:], version=importlib.metadata.version("delayed-ilqr"),
                created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                settings=settings, files=files)


class Output:
    """An ``--out`` folder written atomically: `open` (before computing) checks it and
    makes a hidden staging folder beside it; the command writes into ``staging``; `commit`
    adds manifest.json and renames the staging folder to ``out``, replacing an old one whole."""

    def __init__(self, out: Optional[pathlib.Path], overwrite: bool):
        self.out, self.overwrite, self.staging = out, overwrite, None

    def open(self) -> "Output":
        if self.out is None:
            return self
        out = self.out
        if out.exists() and not out.is_dir():
            raise click.BadParameter(f"{out} exists and is not a folder", param_hint="'--out'")
        if out.is_dir() and any(out.iterdir()) and not self.overwrite:
            raise click.BadParameter(f"{out} is not empty; pass --overwrite to replace it whole",
                                     param_hint="'--out'")
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            self.staging = out.parent / f".{out.name}.partial-{os.getpid()}"
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging.mkdir()
        except OSError as exc:
            raise click.BadParameter(f"cannot create {out}: {exc.strerror or exc}", param_hint="'--out'") from None
        return self

    def commit(self, settings: dict) -> list[str]:
        """Writes manifest.json, moves the staging folder to ``out``; returns the file names."""
        files = sorted(str(f.relative_to(self.staging)) for f in self.staging.rglob("*") if f.is_file())
        sizes = {f: (self.staging / f).stat().st_size for f in files}
        write_text(self.staging / "manifest.json", json.dumps(manifest(settings, sizes), indent=2) + "\n")
        old = None
        with interrupts.deferred(str(self.out)):        # not cut by Ctrl-C or SIGTERM: raised after it
            if self.out.exists():
                old = self.out.parent / f".{self.out.name}.old-{os.getpid()}"
                self.out.rename(old)
            self.staging.rename(self.out)
            self.staging = None
            if old is not None:
                shutil.rmtree(old)
        return files + ["manifest.json"]

    def __enter__(self) -> "Output":
        return self.open()

    def __exit__(self, *exc_info):       # an error or an interrupt: the staging folder goes
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None


def out_option(**kwargs):
    def decorate(f):
        f = click.option("--overwrite", is_flag=True,
                         help="Replace a non-empty --out folder whole (its old files are removed).")(f)
        return click.option("--out", type=OUT_TYPE, **kwargs)(f)
    return decorate


def warn_not_converged(results) -> bool:
    failed = [r for r in results if not r.converged]
    for r in failed:
        click.echo(f"warning: the {r.controller} solve at delay {delay_text(r.problem)} did not converge "
                   f"({r.status}): {r.message}", err=True)
    return bool(failed)


def study_settings(model, noise, trials, seed, substeps) -> dict:
    return dict(model=model, noise=bool(noise), trials=int(trials), seed=int(seed), substeps=int(substeps))


def kwargs_settings(kwargs: dict) -> dict:
    """The factory's keyword arguments for the JSON settings (absent when there are none)."""
    if not kwargs:
        return {}
    return dict(params={k: v if _json_ready(v) else repr(v) for k, v in kwargs.items()})


def _json_ready(value) -> bool:
    try:
        json.dumps(value, allow_nan=False)          # tuples become lists
    except (TypeError, ValueError):
        return False
    return True
