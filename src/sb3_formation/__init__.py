"""sb3-formation: one shared Stable-Baselines3 PPO policy flies a team of robots in formation around obstacles.

The package is layered; each layer imports only from the layers below it (``tests/test_layers.py`` checks it):

- :mod:`sb3_formation.utils`: atomic files, worker processes and shared arrays (standard library, numpy, PyYAML);
- :mod:`sb3_formation.env`: the task (config, geometry, world, sensors, observations, rewards, scenarios, the PettingZoo
  env, rendering); numpy, numba, Pymunk and Pillow only, no torch;
- :mod:`sb3_formation.controllers`: the policy seam (anything that acts) and hand-written controllers; no torch;
- :mod:`sb3_formation.safety`: the safety filter of control barrier functions in front of any policy, its QP solver
  and ``SafePolicy`` (``docs/safety.md``); no torch;
- :mod:`sb3_formation.runtime`: an exported ONNX policy run with onnxruntime (``docs/export.md``); no torch;
- :mod:`sb3_formation.ros`: an agent node per robot and the simulator as a node over ROS 2 (``docs/deployment.md``);
  rclpy from the ``ros`` extra, no torch;
- :mod:`sb3_formation.sb3`: the Stable-Baselines3 layer (VecEnv, normaliser, policies, recurrent PPO, callbacks, ONNX
  export);
- :mod:`sb3_formation.experiment`: recipes, settings, run folders, training, evaluation, policy targets, sweeps;
- :mod:`sb3_formation.viz`: figures and videos; :mod:`sb3_formation.cli` on top.

The names below are re-exported lazily: ``import sb3_formation`` loads nothing heavy until a name is used.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: Public name -> the module that defines it.
_EXPORTS: dict[str, str] = {
    "TASKS": "sb3_formation.env.config",
    "REWARD_TERMS": "sb3_formation.env.config",
    "FormationConfig": "sb3_formation.env.config",
    "FormationEnv": "sb3_formation.env.formation_env",
    "PlacementError": "sb3_formation.env.scenarios",
    "Scenario": "sb3_formation.env.scenarios",
    "TeamState": "sb3_formation.env.state",
    "FormationPolicy": "sb3_formation.sb3.policies",
    "FormationVecEnv": "sb3_formation.sb3.vec_env",
    "ScaleNormalizeVecEnv": "sb3_formation.sb3.normalization",
    "make_formation_vec_env": "sb3_formation.sb3.vec_env",
    "load_policy": "sb3_formation.experiment.targets",
    "load_pretrained": "sb3_formation.experiment.pretrained",
    "pretrained_names": "sb3_formation.experiment.pretrained",
    "load_recipe": "sb3_formation.experiment.recipes",
    "OnnxPolicy": "sb3_formation.runtime",
    "export_onnx": "sb3_formation.sb3.onnx_export",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'sb3_formation' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
