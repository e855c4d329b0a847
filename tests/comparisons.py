"""What the reference tests share: the relative error they compare with, and the record of the
worst difference a module saw, printed when the module finishes (so a run shows how close the
library came to its reference, not only that it passed)."""
from __future__ import annotations

import numpy as np
import pytest


def rel_err(a, b) -> float:
    """max |a - b| / max |b| (absolute when b is all zero); 0 for empty arrays."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, (a.shape, b.shape)
    if a.size == 0:
        return 0.0
    scale = float(np.max(np.abs(b)))
    diff = float(np.max(np.abs(a - b)))
    return diff / scale if scale > 0 else diff


def solution_errors(sol, ref) -> dict:
    """`rel_err` of two solutions' commands, states, costs and gains (state and delay feedback), by name."""
    return dict(u=rel_err(sol.u, ref.u), x=rel_err(sol.x, ref.x), cost=rel_err(sol.cost, ref.cost),
                expected_cost=rel_err(sol.expected_cost, ref.expected_cost),
                L=rel_err(sol.policy.state_feedback, ref.policy.state_feedback),
                M=rel_err(sol.policy.delay_feedback, ref.policy.delay_feedback))


class WorstDifference:
    """The largest relative difference a test module saw, and where (``record``); its
    :meth:`fixture` prints it at the end of the module."""

    def __init__(self, label: str):
        self.label, self.rel, self.where = label, 0.0, ""

    def record(self, rel: float, where: str) -> None:
        if rel > self.rel:
            self.rel, self.where = rel, where

    def fixture(self):
        """A module-scoped autouse fixture; assign it to a name in the test module."""
        @pytest.fixture(scope="module", autouse=True)
        def report_worst(pytestconfig):
            yield
            reporter = pytestconfig.pluginmanager.getplugin("terminalreporter")
            capture = pytestconfig.pluginmanager.getplugin("capturemanager")
            if reporter is not None and capture is not None and self.where:
                with capture.global_and_fixture_disabled():
                    reporter.write_line(f"\n{self.label} {self.rel:.3g} ({self.where})")

        return report_worst
