"""What a model tells studies, reports and figures about itself: [`ModelMetadata`][delayed_ilqr.models.metadata.ModelMetadata].

A factory attaches one to the problem it returns (``Problem.metadata``), so that the delay study,
the center-out study and the figures read labels, units, the task space and the warm start from
the problem instead of switching on its name. A problem without metadata (a user's own plant) gets
indexed labels ``x[i]``, ``u[j]``, no task space and zero initial commands.

Metadata is static data of the problem (pytree auxiliary data, part of the compilation key), so
every field is hashable and compared by value: tuples of strings, and callables that are frozen
dataclasses or module-level functions.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import jax.numpy as jnp
import numpy as np

__all__ = ["ModelMetadata", "TaskSpace", "StateComponents", "CostParameter", "labels", "task_space",
           "task_position", "task_target", "default_u_init"]


@dataclass(frozen=True)
class StateComponents:
    """The task map that picks state components: ``x[..., indices]`` (e.g. the point mass's position)."""

    indices: tuple

    def __call__(self, x):
        return jnp.asarray(x)[..., list(self.indices)]


@dataclass(frozen=True)
class CostParameter:
    """A task target read from the cost's parameters: ``problem.cost.params[key]``."""

    key: str

    def __call__(self, problem):
        return problem.cost.params[self.key]


@dataclass(frozen=True)
class TaskSpace:
    """The space a task is judged in, and the map from states into it.

    Attributes:
        map: ``map(x) -> [..., m]`` for states x [..., n] (``jax.numpy``; leading axes broadcast).
        name: what the map gives, e.g. "hand position"; the endpoint error is "<name> error".
        unit: the unit of every component, e.g. "m".
        point: the point the map locates, named on figure axes ("hand" gives "hand x [m]").
        target: ``target(problem) -> [m]``, the task's goal; None: ``map(problem.cost.x_target)``
            (a [`QuadraticCost`][delayed_ilqr.QuadraticCost]).
        paths: whether paths in this space get a figure of their own (``plot.plot_hand_paths``):
            true where they are not already drawn as states (the arms' hand, not the point mass's
            position).
    """

    map: Callable
    name: str
    unit: str
    point: str
    target: Optional[Callable] = None
    paths: bool = False


@dataclass(frozen=True)
class ModelMetadata:
    """Labels, task space and warm start of a model (see the module docstring).

    Attributes:
        state_labels: [n] names with units, e.g. "shoulder angle q1 [rad]".
        control_labels: [d] names with units, e.g. "shoulder torque u1 [N m]".
        task: the [`TaskSpace`][delayed_ilqr.models.metadata.TaskSpace] the endpoint error is measured in, or None (the studies then
            report the final cost instead of a distance over states of mixed units).
        u_init: ``u_init(problem) -> [K, d]``, the recommended initial commands of a solve, or None
            (zeros).
        noise: the name of the noise preset the factory built (e.g. ``"human"``, ``"benchmark"``;
            ``"custom"`` for a level given as ``sigma_u``), None without noise or without presets;
            its level is in ``problem.noise``. Reports and saved files record it.
    """

    state_labels: tuple
    control_labels: tuple
    task: Optional[TaskSpace] = None
    u_init: Optional[Callable] = None
    # a name for reports, not structure: problems that differ only in their noise level (a sweep
    # over sigma_u that crosses a preset's level) keep equal metadata and share one compiled solver
    noise: Optional[str] = field(default=None, compare=False)

    def __post_init__(self):
        for field in ("state_labels", "control_labels"):
            value = getattr(self, field)
            if not isinstance(value, tuple) or not all(isinstance(s, str) for s in value):
                raise TypeError(f"{field} must be a tuple of strings; got {value!r}")
        if self.task is not None and not isinstance(self.task, TaskSpace):
            raise TypeError(f"task must be None or a TaskSpace; got {type(self.task).__name__}")
        if self.noise is not None and not isinstance(self.noise, str):
            raise TypeError(f"noise must be None or a preset's name; got {self.noise!r}")


def labels(problem) -> tuple[list[str], list[str]]:
    """(state labels [n], control labels [d]) of the problem's metadata, else ``x[i]`` / ``u[j]``."""
    meta = getattr(problem, "metadata", None)
    if meta is not None and len(meta.state_labels) == problem.n_states \
            and len(meta.control_labels) == problem.n_controls:
        return list(meta.state_labels), list(meta.control_labels)
    return [f"x[{i}]" for i in range(problem.n_states)], [f"u[{j}]" for j in range(problem.n_controls)]


def task_space(problem) -> Optional[TaskSpace]:
    """The problem's [`TaskSpace`][delayed_ilqr.models.metadata.TaskSpace], or None."""
    meta = getattr(problem, "metadata", None)
    return None if meta is None else meta.task


def task_position(problem, x) -> Optional[np.ndarray]:
    """Task-space positions [..., m] of states x [..., n], or None without a task space."""
    task = task_space(problem)
    if task is None:
        return None
    return np.asarray(task.map(jnp.asarray(x)))


def task_target(problem) -> Optional[np.ndarray]:
    """The task's goal [m] (see `TaskSpace.target`), or None when there is none to read."""
    task = task_space(problem)
    if task is None:
        return None
    if task.target is not None:
        return np.asarray(task.target(problem))
    x_target = getattr(problem.cost, "x_target", None)
    return None if x_target is None else np.asarray(task.map(jnp.asarray(x_target)))


def default_u_init(problem):
    """The model's recommended initial commands [K, d] (``ModelMetadata.u_init``), or None (zeros)."""
    meta = getattr(problem, "metadata", None)
    if meta is None or meta.u_init is None:
        return None
    return meta.u_init(problem)
