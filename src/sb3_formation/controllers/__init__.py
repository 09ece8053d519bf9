"""The policy seam (anything that acts in the formation env) and hand-written controllers; numpy only, no torch.

:data:`CONTROLLERS` names the controllers that ``controller:<name>`` targets of the CLI resolve to.
"""

from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.controllers.classical import ClassicalController, ClassicalGains
from sb3_formation.controllers.planner import PlannerGains, PrivilegedPlanner
from sb3_formation.controllers.random import RandomController

#: Controllers by name: ``controller:<name>`` on the command line, :func:`sb3_formation.load_policy` in Python.
CONTROLLERS: dict[str, type[Controller]] = {
    "classical": ClassicalController,
    "random": RandomController,
    "privileged-planner": PrivilegedPlanner,
}

__all__ = [
    "CONTROLLERS",
    "ClassicalController",
    "ClassicalGains",
    "Controller",
    "PlannerGains",
    "PrivilegedPlanner",
    "RandomController",
    "TeamPolicy",
]
