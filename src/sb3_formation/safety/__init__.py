"""Constraint satisfaction (the thesis's future work): a safety filter of control barrier functions that any policy's
actions pass through (``docs/safety.md``). Numpy and numba only, like the environment: the runtime and a robot use it
without torch."""

from sb3_formation.safety.filter import FilterReport, SafetyFilter, SafetyGains

__all__ = ["FilterReport", "SafetyFilter", "SafetyGains"]
