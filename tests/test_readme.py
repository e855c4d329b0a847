"""The README's LQG example runs and prints three agreeing numbers (J(0), exact cost, Monte Carlo)."""
import contextlib
import io
import pathlib


def test_readme_lqg_example_runs_and_agrees():
    text = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    code = text.split("## The LQG layer in ten lines")[1].split("```python")[1].split("```")[0]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    expected, exact, monte_carlo = (float(v) for v in out.getvalue().split())
    assert abs(expected - exact) <= 1e-10 * abs(exact)
    assert abs(monte_carlo - exact) <= 0.02 * abs(exact)     # 10000 trials: a few standard errors


def test_readme_sensor_example_runs_and_agrees():
    """The README's delayed-sensor example, run after the LQG example it continues: the design's
    expected cost, the exact cost of the pair and the Monte Carlo mean agree."""
    text = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    first = text.split("## The LQG layer in ten lines")[1].split("```python")[1].split("```")[0]
    second = text.split("### Delayed, noisy sensors: the estimator")[1].split("```python")[1].split("```")[0]
    namespace, out = {}, io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()):
        exec(compile(first, "README.md", "exec"), namespace)
    with contextlib.redirect_stdout(out):
        exec(compile(second, "README.md", "exec"), namespace)
    expected, exact, monte_carlo = (float(v) for v in out.getvalue().split())
    assert abs(expected - exact) <= 1e-10 * abs(exact)
    assert abs(monte_carlo - exact) <= 0.02 * abs(exact)     # 10000 trials: a few standard errors


def test_readme_nonlinear_sensor_example_runs_and_agrees():
    """The nonlinear sensors example: the Monte Carlo on the nonlinear arm lies within 4 standard
    errors of the expected cost of its linearisation, and the first command to respond to the
    kick of x_16 is u_21 (l_s = 5)."""
    text = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    code = text.split("### Delayed, noisy sensors in the nonlinear solver")[1].split("```python")[1].split("```")[0]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), {})
    first_line, second_line = out.getvalue().strip().splitlines()
    expected, monte_carlo, standard_error, first = (float(v) for v in first_line.split())
    assert abs(monte_carlo - expected) <= 4 * standard_error
    assert first == 21
    assert float(second_line) > expected            # seeing less (the hand only, later) costs more
