"""Studies of delayed control: one engine, two studies, one report writer.

The data flow: a model's problem -> designs (problem transforms) -> timed solves -> Monte Carlo
on the plant -> statistics -> tables and files (figures: [`delayed_ilqr.plot`][delayed_ilqr.plot]).

|  |  |
|---|---|
| `designs` | controller designs as problem transforms (aware, ignorant, augmented, noise-aware, deterministic) |
| `engine` | timed solves (one problem, or a batch in one compiled call), Monte Carlo with endpoint errors in the model's task space |
| [`delay_study`][delayed_ilqr.experiments.delay_study] | delay-aware vs delay-ignorant control at several delays |
| [`center_out`][delayed_ilqr.experiments.center_out] | center-out reaching with the six-muscle arm, one batched solve per delay |
| `perturbation` | a hand kick mid-reach: mean corrective responses against the sensory delay |
| [`fitting`][delayed_ilqr.experiments.fitting] | inverse optimal control: cost weights and noise scales fitted to reach statistics through the solver's gradients, the delay by a profile |
| [`delay_fitting`][delayed_ilqr.experiments.delay_fitting] | the motor delays fitted by gradient with the other parameters (fractional delays), confidence intervals by a parametric bootstrap |
| `delay_text` | a delay as every report, figure and file name writes it: "50 ms", "[50, 70] ms" per channel, exact between steps, a jitter with its distribution |
| `tables` | every table row, as plain text or markdown (Monte Carlo mean [95 % CI] and median beside the local, linearised prediction; its 2x warnings) |
| `report` | JSON records, NPZ arrays, markdown reports and figures on disk |

The gallery, classic experiments of human motor control (each with its published numbers,
an analysis function, a figure in `delayed_ilqr.plot.gallery` and a `delayed-ilqr` command), all
on the models' default delays, sensors and noise (`reach_tasks.reach`):

|  |  |
|---|---|
| `reach_tasks` | hand-space reaches of both arms; bar target; hold from a movement time; the target as state |
| `responses` | analysis: response onsets, endpoint ellipses, the Fitts fit |
| `kick` | a mid-reach kick: command latency against the loop, final error |
| `target_jump` | target jumps at several times before the end (Liu & Todorov 2007) |
| `fitts` | the movement time the model chooses against log2(2D/W), per delay |
| `minimal_intervention` | bar against point target: task-irrelevant / relevant endpoint SD |
| `delay_growth` | cost, endpoint error and scatter against the motor and the sensory delay, beside the linearised prediction |

"""
