"""Importing ``delayed_ilqr`` leaves the user's process as it was, and the library refuses float32
with the one line to add. Each check runs in a fresh Python process: this one has float64 on and
XLA's flags set (conftest.py)."""
import json
import os
import subprocess
import sys
import textwrap

import pytest

from delayed_ilqr._precision import ENABLE_X64


def run_fresh(code: str) -> subprocess.CompletedProcess:
    """``code`` in a new interpreter with this one's path, without XLA_FLAGS and JAX_ENABLE_X64."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    env["PYTHONPATH"] = os.pathsep.join(sys.path)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True,
                          text=True, timeout=300, check=False)


def last_json(result: subprocess.CompletedProcess):
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_import_changes_no_environment_variable_and_no_jax_setting():
    result = run_fresh("""
        import json, os, jax
        before = dict(os.environ), dict(jax.config.values)
        import delayed_ilqr, delayed_ilqr.cli, delayed_ilqr.experiments, delayed_ilqr.plot
        from jax._src import xla_bridge
        after = dict(os.environ), dict(jax.config.values)
        print(json.dumps({"environ": before[0] == after[0], "config": before[1] == after[1],
                          "x64": jax.config.jax_enable_x64, "backend": xla_bridge.backends_are_initialized()}))
    """)
    # nothing changed, and no JAX computation ran: configure_cpu after the import still works
    assert last_json(result) == {"environ": True, "config": True, "x64": False, "backend": False}


def test_configure_cpu_in_a_fresh_process_sets_the_flags_and_then_warns_when_too_late():
    result = run_fresh("""
        import json, os, warnings
        import delayed_ilqr, jax
        first, second = delayed_ilqr.configure_cpu(), delayed_ilqr.configure_cpu()
        flags = os.environ["XLA_FLAGS"]
        del os.environ["XLA_FLAGS"]
        jax.numpy.zeros(1).block_until_ready()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            late = delayed_ilqr.configure_cpu()
        print(json.dumps({"first": first, "second": second, "flags": flags, "late": late,
                          "warned": [str(w.message) for w in caught], "after": "XLA_FLAGS" in os.environ}))
    """)
    out = last_json(result)
    assert out["first"] == ["--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000",
                            "--xla_cpu_experimental_ynn_fusion_type=-individual_dot"]
    assert out["second"] == [] and out["flags"] == " ".join(out["first"])
    assert out["late"] == [] and out["after"] is False
    assert len(out["warned"]) == 1 and "before any JAX computation" in out["warned"][0]


def test_models_is_an_attribute_of_the_package():
    result = run_fresh(f"""
        import jax
        {ENABLE_X64}
        import delayed_ilqr
        problem = delayed_ilqr.models.arm2(delay=0.1)
        print(problem.delay_steps)
    """)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["10"]


ENTRY_POINTS = ["Problem", "lqg.DelayedLQG", "solve", "simulate", "lqg.backward_pass",
                "lqg.augmented_backward_pass", "lqg.policy_cost", "lqg.simulate_lqg",
                "prediction.closed_loop_prediction", "statistical.statistical_feedback"]


def test_every_entry_point_refuses_float32_with_the_line_to_add():
    # the objects are made, and each compiled function run once, in float64; then without it
    result = run_fresh("""
        import json, jax, numpy as np
        import delayed_ilqr as di
        from delayed_ilqr import lqg
        from delayed_ilqr.models import point_mass
        from delayed_ilqr.prediction import closed_loop_prediction
        from delayed_ilqr.statistical import statistical_feedback

        K, n, d = 5, 2, 1
        arrays = dict(A=np.tile(np.eye(n), (K, 1, 1)), B0=np.zeros((K, n, d)), B1=np.ones((K, n, d)),
                      c=None, C0=None, C1=None, d_tilde=np.zeros(K + 1), d=np.zeros((K + 1, n)),
                      D=np.tile(np.eye(n), (K + 1, 1, 1)), e=np.zeros((K, d)), E=np.ones((K, d, d)),
                      delay_steps=2)
        with jax.enable_x64(True):
            problem = point_mass(delay=0.03)
            policy = di.solve(problem).policy
            linear = lqg.DelayedLQG(**arrays)
            gains, _ = lqg.backward_pass(linear)
            lqg.augmented_backward_pass(linear)
        calls = {
            "Problem": lambda: point_mass(delay=0.03),
            "lqg.DelayedLQG": lambda: lqg.DelayedLQG(**arrays),
            "solve": lambda: di.solve(problem),
            "simulate": lambda: di.simulate(problem, policy, 2),
            "lqg.backward_pass": lambda: lqg.backward_pass(linear),
            "lqg.augmented_backward_pass": lambda: lqg.augmented_backward_pass(linear),
            "lqg.policy_cost": lambda: lqg.policy_cost(linear, gains),
            "lqg.simulate_lqg": lambda: lqg.simulate_lqg(linear, gains, 2),
            "prediction.closed_loop_prediction": lambda: closed_loop_prediction(problem, policy),
            "statistical.statistical_feedback": lambda: statistical_feedback(problem, policy),
        }
        refusals = {}
        for name, call in calls.items():
            try:
                call()
                refusals[name] = None
            except ValueError as exc:
                refusals[name] = str(exc)
        print(json.dumps(refusals))
    """)
    refusals = last_json(result)
    assert sorted(refusals) == sorted(ENTRY_POINTS)
    for name, message in refusals.items():
        assert message is not None, f"{name} ran in float32"
        assert f"delayed_ilqr.{name} needs float64" in message and ENABLE_X64 in message


@pytest.mark.slow
def test_the_command_line_turns_float64_on_itself():
    result = run_fresh("""
        from delayed_ilqr.cli import main
        main(["solve", "point_mass", "--delay", "0.03"])
    """)
    assert result.returncode == 0, result.stderr
    assert "CONVERGED" in result.stdout
