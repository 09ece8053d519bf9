"""Every old spelling still works for one release and warns, naming its replacement (CHANGELOG.md)."""

from __future__ import annotations

import pytest

import sb3_formation
from sb3_formation import FormationConfig, make_formation_vec_env


def test_formation_config_preset_is_task() -> None:
    with pytest.warns(FutureWarning, match=r"FormationConfig\.preset is deprecated .* use FormationConfig\.task"):
        config = FormationConfig.preset("ch4-team", n_agents=5)
    assert config == FormationConfig.task("ch4-team", n_agents=5)


@pytest.mark.parametrize("module", ["sb3_formation", "sb3_formation.env", "sb3_formation.env.config"])
def test_presets_are_tasks(module: str) -> None:
    imported = __import__(module, fromlist=["TASKS"])
    with pytest.warns(FutureWarning, match=r"PRESETS is deprecated .* use .*TASKS"):
        presets = imported.PRESETS
    assert presets is sb3_formation.TASKS and set(presets) == {"ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"}


def test_make_formation_vec_env_preset_is_task() -> None:
    with pytest.warns(FutureWarning, match=r"make_formation_vec_env\(preset=\.\.\.\) is deprecated .*\(task=\.\.\.\)"):
        venv = make_formation_vec_env(preset="ch4-individual", n_envs=2, normalize=False)
    assert venv.config == FormationConfig.task("ch4-individual") and venv.num_envs == 6
    venv.close()
