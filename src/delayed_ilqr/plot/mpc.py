"""Receding-horizon closed loops: each controller's states and commands against time."""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ._common import figure
from .solution import state_labels


def plot_closed_loop(problem, runs: Mapping[str, object], trial: int = 0):
    """States (one panel each, with the reference dashed) and commands of trial ``trial`` of every
    closed loop in ``runs`` ({label: [`ClosedLoop`][delayed_ilqr.mpc.ClosedLoop]}) against time (s)."""
    n, d = problem.n_states, problem.n_controls
    labels, controls = state_labels(problem)
    fig = figure(figsize=(10, 2.0 * (n + d)), layout="constrained")
    axes = fig.subplots(n + d, 1, sharex=True)
    for label, run in runs.items():
        x, u = np.asarray(run.x[trial]), np.asarray(run.u[trial])
        t = problem.dt * np.arange(x.shape[0])
        for i in range(n):
            axes[i].plot(t, x[:, i], label=label)
        for j in range(d):
            axes[n + j].step(t[:-1], u[:, j], where="post", label=label)
    reference = np.asarray(next(iter(runs.values())).reference)
    t = problem.dt * np.arange(reference.shape[0])
    for i in range(n):
        axes[i].plot(t, reference[:, i], "k--", lw=1.0, label="reference")
        axes[i].set_ylabel(labels[i], fontsize=8)
    for j in range(d):
        axes[n + j].set_ylabel(controls[j], fontsize=8)
    axes[0].legend(fontsize=7, ncols=3)
    axes[-1].set_xlabel("time [s]")
    return fig
