"""The study engine's pieces without a solve: designs as problem transforms, endpoint errors in the
model's task space (and the final cost for a plant without one), and the tables."""
import math

import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.experiments import designs, tables
from delayed_ilqr.experiments.engine import endpoint_description, endpoint_error
from delayed_ilqr.models import arm2, arm2_muscle6, hand_position, pendulum, point_mass


def test_designs_transform_the_plant_and_force_the_method():
    plant = arm2(delay=0.05, noise="benchmark")
    aware, options = designs.design(plant, "aware")
    assert aware is plant and options == di.Options()
    ignorant, _ = designs.design(plant, "ignorant")
    assert ignorant.delay_steps == 0 and ignorant.noise == plant.noise and ignorant.metadata == plant.metadata
    _, options = designs.design(plant, "augmented", di.Options(max_iterations=7))
    assert options.method == "augmented" and options.max_iterations == 7
    deterministic, _ = designs.design(plant, "deterministic")
    assert deterministic.noise is None and deterministic.delay_steps == plant.delay_steps
    with pytest.raises(ValueError, match="design must be one of"):
        designs.design(plant, "ilqr")
    with pytest.raises(TypeError, match="options must be a delayed_ilqr.Options; got dict"):
        designs.design(plant, "aware", {})


def test_endpoint_errors_are_distances_in_the_task_space():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((6, 4))
    arm = arm2()
    target = hand_position(jnp.asarray(arm.cost.x_target[:2]))
    np.testing.assert_array_equal(endpoint_error(arm, x),
                                  np.linalg.norm(np.asarray(hand_position(jnp.asarray(x[:, :2]))) - target, axis=-1))
    assert endpoint_description(arm) == ("hand position error", "m")
    assert endpoint_description(point_mass()) == ("position error", "m")
    np.testing.assert_array_equal(endpoint_error(point_mass(), x), np.linalg.norm(x[:, :2] - [0.2, 0.1], axis=-1))
    assert endpoint_description(pendulum()) == ("angle error", "rad")
    np.testing.assert_array_equal(endpoint_error(pendulum(), x[:, :2]), np.abs(x[:, 0] - math.pi))
    muscle = arm2_muscle6(target=(0.0, 0.5))
    assert endpoint_description(muscle) == ("hand position error", "m")


def test_a_plant_without_metadata_is_judged_by_its_final_cost_not_a_mixed_unit_norm():
    bare = point_mass().replace(metadata=None)
    x = np.random.default_rng(1).standard_normal((5, 4))
    assert endpoint_description(bare) == ("final cost", "")
    expected = [float(bare.cost.final(jnp.asarray(xi))) for xi in x]
    np.testing.assert_allclose(endpoint_error(bare, x), expected, rtol=1e-14)


def test_tables_format_text_and_markdown_from_one_set_of_rows():
    table = (["a", "long header"], [["1", "x"], ["22", "yy"]])
    assert tables.text_table(table) == "a   long header\n--  -----------\n1   x\n22  yy"
    assert tables.markdown_table(table) == "| a | long header |\n|---|---|\n| 1 | x |\n| 22 | yy |"
    assert tables.num(float("inf")) == "inf" and tables.num(float("nan")) == "nan" and tables.num(0.123456) == "0.1235"
    assert tables.unit_scale("m") == (1e3, "mm") and tables.unit_scale("rad") == (1.0, "rad")
