"""Other libraries take the environment as it is (issue 16): TorchRL's PettingZoo wrapper (and so BenchMARL)."""

from __future__ import annotations

import warnings

import pytest
import torch

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.config import REWARD_INFO_KEYS

PRESETS = ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"]


@pytest.mark.parametrize("preset", PRESETS)
def test_torchrl_wraps_checks_and_rolls_out_every_preset(preset: str) -> None:
    """README "Using it with other libraries": TorchRL's ``PettingZooWrapper`` builds, ``check_env_specs`` passes and
    a 50-step rollout runs; the flat reward terms arrive as one tensor each."""
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # TorchRL names the PettingZoo version it was tested with
        env = PettingZooWrapper(FormationEnv(FormationConfig.preset(preset, stage=3)), categorical_actions=False, seed=0)
    check_env_specs(env)
    rollout = env.rollout(50)
    n_agents = FormationConfig.preset(preset).n_agents
    assert rollout.batch_size == torch.Size([50])
    assert rollout["next", "agent", "reward"].shape == (50, n_agents, 1)
    info = rollout["next", "agent", "info"]
    assert all(info[key].shape == (50, n_agents) for key in REWARD_INFO_KEYS)
    assert torch.isfinite(rollout["next", "agent", "observation"]).all()
