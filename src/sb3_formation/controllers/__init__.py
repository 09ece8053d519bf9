"""The policy seam (anything that acts in the formation env), hand-written controllers and residual policies on them
(:class:`ResidualAdapter`: a controller's action plus a learned correction); numpy only, no torch.

:data:`CONTROLLERS` names the controllers that ``controller:<name>`` targets of the CLI resolve to.
"""

from typing import Any

from sb3_formation.controllers.base import Controller, TeamPolicy
from sb3_formation.controllers.classical import ClassicalController, ClassicalGains
from sb3_formation.controllers.crowd import CrowdController, CrowdGains
from sb3_formation.controllers.planner import PlannerGains, PrivilegedPlanner
from sb3_formation.controllers.random import RandomController
from sb3_formation.controllers.residual import ResidualAdapter, ResidualPolicy
from sb3_formation.controllers.shrinking import ShrinkingController, ShrinkingGains
from sb3_formation.env.config import FormationConfig

#: Controllers by name: ``controller:<name>`` on the command line, :func:`sb3_formation.load_policy` in Python.
CONTROLLERS: dict[str, type[Controller]] = {
    "classical": ClassicalController,
    "random": RandomController,
    "privileged-planner": PrivilegedPlanner,
    "shrinking": ShrinkingController,
    "crowd": CrowdController,
}


def controller_from_spec(spec: dict[str, Any], config: FormationConfig) -> Controller:
    """The controller a recipe block (or an exported policy's residual) names: ``controller`` and optional ``gains``.

    :param spec: ``controller`` (a name of :data:`CONTROLLERS`) and optionally ``gains`` (its keyword arguments)
    :param config: the task the controller acts in
    :raises ValueError: an unknown controller, or gains that are not a mapping
    """
    name = spec["controller"]
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {name!r}; controllers: {', '.join(sorted(CONTROLLERS))}")
    gains = spec.get("gains") or {}
    if not isinstance(gains, dict):
        raise ValueError(f"gains must be a mapping of gain names to values, got {gains!r}")
    return CONTROLLERS[name](config, **gains)


__all__ = [
    "CONTROLLERS",
    "ClassicalController",
    "ClassicalGains",
    "Controller",
    "CrowdController",
    "CrowdGains",
    "PlannerGains",
    "PrivilegedPlanner",
    "RandomController",
    "ResidualAdapter",
    "ResidualPolicy",
    "ShrinkingController",
    "ShrinkingGains",
    "TeamPolicy",
    "controller_from_spec",
]
