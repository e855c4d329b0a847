"""The delayed feedback law and the closed-loop step, as the solver's loops use them: they live in
the LQG layer (``delayed_ilqr.lqg.law``); this module names them for ``ilqg``."""
from ..lqg.law import augmented_feedback, closed_loop_affine, closed_loop_step, delayed_law, write_slot

__all__ = ["delayed_law", "write_slot", "closed_loop_step", "augmented_feedback", "closed_loop_affine"]
