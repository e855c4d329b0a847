"""Delay-aware receding-horizon control: the controller in the loop, with the commands in flight
fed back.

|  |  |
|---|---|
| controller.py | ``MPC`` (immutable configuration), its state, the pure compiled tick |
| estimation.py | with delayed sensors, the controller's delayed filter (its estimate of the present state) |
| strategies.py | the compensations of the delay as strategies of one controller |
| receding.py | the problem one tick solves: restarted at t_k, the commands in flight first |
| reference.py | the reference r(t): constant, sampled, or a function of time |
| closed_loop.py | ``simulate``: controller and plant as one scan over ticks, vmapped over trials |

"""
from .controller import MPC, ControllerState, Tick, TickLaw
from .estimation import FilterState
from .strategies import COMPENSATIONS
from .closed_loop import ClosedLoop, simulate

__all__ = ["MPC", "ControllerState", "Tick", "TickLaw", "FilterState", "COMPENSATIONS", "ClosedLoop", "simulate"]
