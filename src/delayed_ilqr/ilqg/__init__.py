"""iLQG with control delay around the structured LQG of [`delayed_ilqr.lqg`][delayed_ilqr.lqg].

Data flow of one iteration, one module per job:

| module | its job |
|---|---|
| linearize.py | eq. (3)-(4): rollout, cost, the LQG of a nominal (stored or step by step) |
| backward.py | the backward pass of an iteration: linearise, Theorem 1 (or augmentation), the solver's gain rules (box limits, noise) |
| candidates.py | the nonlinear plant in closed loop around the nominal (step size alpha) |
| line_search.py | merit, candidate scores, the LQG's predicted change, Tassa's line search |
| regularization.py | Tassa's lambda schedule |
| batching.py | the CPU batching rule (vmap as a loop over problems) |
| solver.py | the loop: backward pass, search, regularisation, stop test; ``solve`` |

"""
