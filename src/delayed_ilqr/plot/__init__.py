"""Figures for solutions, Monte Carlo runs and the studies.

Every function builds a `matplotlib.figure.Figure` directly (no ``pyplot``: no global
state, no backend switch in the caller's session, never ``show()``) and returns it; save it with
``fig.savefig("name.png")`` (rendered by Agg). matplotlib is imported inside the functions, so
importing [`delayed_ilqr`][delayed_ilqr] does not import it. Labels, units and the task space (e.g. the hand
position of the arms) come from the model's metadata ([`delayed_ilqr.models.metadata`][delayed_ilqr.models.metadata]).

|  |  |
|---|---|
| `solution` | states and commands against time; convergence of solves |
| `delay_study` | cost and endpoint error against the delay; task-space (hand) paths |
| `center_out` | center-out hand paths, speed profiles, endpoint ellipses in mm, cost and spread against the delay; excitation patterns |
| `perturbation` | mean corrective responses to a kick against the sensory delay |
| `sweep` | a sweep's Dataset: Monte Carlo cost and endpoint error against a grid axis |
| `gallery` | the gallery's experiments: kick, target jump, Fitts, minimal intervention |

``delay_study_figures``, ``center_out_figures`` and ``perturbation_figures`` give a study's figures
by file name.
"""
from ._common import COLORS
from .center_out import (CAPTIONS, center_out_figures, plot_center_out, plot_center_out_vs_delay,
                         plot_endpoints, plot_excitations, plot_speed_profiles)
from .delay_study import delay_study_figures, draws_paths, plot_delay_study, plot_hand_paths
from .perturbation import perturbation_figures, plot_perturbation
from .solution import plot_convergence, plot_trajectories, state_labels
from .sweep import plot_sweep

__all__ = ["plot_trajectories", "plot_hand_paths", "plot_delay_study", "plot_convergence", "plot_center_out",
           "plot_speed_profiles", "plot_endpoints", "plot_center_out_vs_delay", "CAPTIONS", "plot_excitations",
           "delay_study_figures", "center_out_figures", "draws_paths", "state_labels", "plot_perturbation",
           "perturbation_figures", "plot_sweep", "COLORS"]
