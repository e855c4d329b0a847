"""Studies of delayed control: one engine, two studies, one report writer.

The data flow: a model's problem -> designs (problem transforms) -> timed solves -> Monte Carlo
on the plant -> statistics -> tables and files (figures: [`delayed_ilqr.plot`][delayed_ilqr.plot]).

| module | its job |
|---|---|
| `designs` | controller designs as problem transforms (aware, ignorant, augmented, noise-aware, deterministic) |
| `engine` | timed solves (one problem, or a batch in one compiled call), Monte Carlo with endpoint errors in the model's task space |
| [`delay_study`][delayed_ilqr.experiments.delay_study] | delay-aware vs delay-ignorant control at several delays |
| [`center_out`][delayed_ilqr.experiments.center_out] | center-out reaching with the six-muscle arm, one batched solve per delay |
| `perturbation` | a hand kick mid-reach: mean corrective responses against the sensory delay |
| [`fitting`][delayed_ilqr.experiments.fitting] | inverse optimal control: cost weights and noise scales fitted to reach statistics through the solver's gradients, the delay by a profile |
| `tables` | every table row, as plain text or markdown |
| `report` | JSON records, NPZ arrays, markdown reports and figures on disk |

"""
