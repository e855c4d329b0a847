"""Several sensors of one problem, each with its own output, noise, delay and period:
``Problem(observation=[Observation(...), Observation(...)])``.

The list is checked and normalised here (`checked_observation`): a single
[`Observation`][delayed_ilqr.Observation] keeps its meaning, a list of one *is* that observation, and
a longer list becomes a [`SensorList`][delayed_ilqr.sensor_list.SensorList]. Sensors with one common
delay are one observation whose output stacks theirs (the delayed filter of ``lqg.estimator``, with
each row's period); sensors with different delays are fused by ``lqg.fusion`` without augmenting
the state (``docs/derivation.md`` §19).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from .observation import Observation, linearized_observation

__all__ = ["SensorList", "checked_observation", "linearized_sensors"]


class SensorList:
    """Several [`Observation`][delayed_ilqr.Observation]s of one problem (made by `checked_observation`).

    It reads as one observation whose output stacks the sensors' outputs in order (``measure``,
    ``jacobian``) and whose noise is block-diagonal (independent sensors): exactly the meaning of the
    list when the delays are equal. ``delay_steps`` is the largest delay, ``period`` one period per
    output row.

    Attributes:
        observations: the sensors (a tuple).
        sizes: the number of outputs of each sensor (static).
    """

    def __init__(self, observations, sizes):
        self.observations, self.sizes = tuple(observations), tuple(int(m) for m in sizes)

    @property
    def delays(self) -> tuple:
        return tuple(o.delay_steps for o in self.observations)

    @property
    def delay_steps(self) -> int:
        """The largest delay: the window the fused filter looks back over."""
        return max(self.delays)

    @property
    def equal_delays(self) -> bool:
        return len(set(self.delays)) == 1

    @property
    def period(self) -> tuple:
        """One period per output row."""
        return sum(((o.period,) * m for o, m in zip(self.observations, self.sizes)), ())

    @property
    def lags(self) -> tuple:
        """One delay per output row."""
        return sum(((o.delay_steps,) * m for o, m in zip(self.observations, self.sizes)), ())

    @property
    def additive(self) -> bool:
        return all(o.additive for o in self.observations)

    def measure(self, x):
        """The stacked outputs [M] of every sensor at one state x."""
        return jnp.concatenate([o.measure(x) for o in self.observations])

    def noise_matrix(self, x):
        """The block-diagonal [M, sum q_a] noise columns at x."""
        return jax.scipy.linalg.block_diag(*(o.noise_matrix(x) for o in self.observations))

    def jacobian(self, x):
        return jnp.concatenate([o.jacobian(x) for o in self.observations])

    def measure_delayed(self, past, v):
        """The rows arriving now: sensor a reads past[L - l_a] (past [L + 1, n] holds x_{k-L}..x_k)
        with its own noise columns of v [sum q_a]; returns [M]."""
        L, out, start = self.delay_steps, [], 0
        for o in self.observations:
            x = past[L - o.delay_steps]
            G = o.noise_matrix(x)
            out.append(o.measure(x) + G @ v[start:start + G.shape[1]])
            start += G.shape[1]
        return jnp.concatenate(out)

    def __repr__(self):
        return "SensorList([" + ", ".join(map(repr, self.observations)) + "])"


jax.tree_util.register_pytree_node(
    SensorList, lambda s: (s.observations, s.sizes), lambda sizes, obs: SensorList(obs, sizes))


def checked_observation(observation, x0, horizon: int):
    """A problem's ``observation`` checked against its state x0 [n] and horizon K, normalised:
    None, one [`Observation`][delayed_ilqr.Observation] (a list of one gives that observation), or a
    [`SensorList`][delayed_ilqr.sensor_list.SensorList]. Raises naming ``observation`` (and the
    index of the sensor at fault), the rule and what was received."""
    if observation is None or isinstance(observation, Observation):
        if observation is not None:
            observation.check(x0, horizon)
        return observation
    if isinstance(observation, SensorList):
        observation = observation.observations
    if not isinstance(observation, (list, tuple)):
        raise TypeError(f"observation must be None or a delayed_ilqr.Observation (or a list of them, one per sensor); got "
                        f"{type(observation).__name__}")
    if len(observation) == 0:
        raise ValueError("observation must be an Observation or a non-empty list of Observations (one per sensor); "
                         "got an empty list")
    sizes = []
    for i, o in enumerate(observation):
        if not isinstance(o, Observation):
            raise TypeError(f"observation[{i}] must be a delayed_ilqr.Observation; got {type(o).__name__}")
        try:
            o.check(x0, horizon)
        except ValueError as exc:
            raise ValueError(f"observation[{i}]: {exc}") from None
        sizes.append(jax.eval_shape(o.measure, jax.ShapeDtypeStruct((x0.shape[0],), jnp.float64)).shape[0])
    return observation[0] if len(observation) == 1 else SensorList(observation, sizes)


def linearized_sensors(sensors: SensorList, xs):
    """Each sensor linearised around the nominal xs [K+1, n] (``linearized_observation``), and the
    nominal outputs stacked [K, M] (row block a: h_a(x_bar_{k-l_a}), the rows arriving at k)."""
    pairs = [linearized_observation(o, xs) for o in sensors.observations]
    return tuple(p[0] for p in pairs), jnp.concatenate([p[1] for p in pairs], axis=1)


