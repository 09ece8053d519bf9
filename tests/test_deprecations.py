"""Every old spelling still works for one release and warns, naming its replacement (CHANGELOG.md)."""

from __future__ import annotations

import pytest

import sb3_formation
import sb3_formation.experiment.recipes
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


def test_cli_preset_flag_and_presets_command_are_recipe(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    from sb3_formation.cli import main

    with pytest.warns(FutureWarning, match=r"sb3-formation presets is deprecated .* use sb3-formation recipes"):
        assert main(["presets"]) == 0
    assert "fast-ch5-bearing" in capsys.readouterr().out
    out = tmp_path / "frame.png"
    arguments = ["rollout", "--preset", "ch4-team", "--episodes", "1", "--max-steps", "3", "--out", str(out)]
    with pytest.warns(FutureWarning, match=r"--preset is deprecated .* use --recipe"):
        assert main(arguments) == 0
    assert "n=3" in capsys.readouterr().out and out.is_file()  # ch4-team's task: teams of 3


def test_load_policy_preset_and_load_setup_are_recipe() -> None:
    from sb3_formation import load_policy

    with pytest.warns(FutureWarning, match=r"load_policy\(preset=\.\.\.\) is deprecated .*load_policy\(recipe=\.\.\.\)"):
        policy = load_policy("controller:classical", preset="ch4-team")
    assert policy.config.n_agents == 3
    with pytest.warns(FutureWarning, match=r"sb3_formation\.load_setup is deprecated .* sb3_formation\.load_recipe"):
        load_setup = sb3_formation.load_setup
    assert load_setup("ch4-team").name == "ch4-team"


def test_old_keys_of_settings_and_recipe_files_are_read(tmp_path) -> None:
    from sb3_formation.experiment.recipes import load_recipe
    from sb3_formation.experiment.settings import TrainSettings, layered_settings

    old = tmp_path / "old-recipe.yaml"
    text = (sb3_formation.experiment.recipes.RECIPES_FOLDER / "fast-ch4-team.yaml").read_text()
    old.write_text(text.replace("  task: ", "  preset: ").replace("n_envs: ", "teams: "))
    with pytest.warns(FutureWarning, match=r"teams: .* is deprecated .* use n_envs:"):
        with pytest.warns(FutureWarning, match=r"env: preset: .* is deprecated .* use env: task:"):
            recipe = load_recipe(old)
    current = load_recipe("fast-ch4-team")
    assert (recipe.n_envs, recipe.config()) == (current.n_envs, current.config())
    settings_file = tmp_path / "config.yaml"
    settings_file.write_text("preset: ch4-team\nseed: 3\n")
    with pytest.warns(FutureWarning, match=r"config.yaml is in the settings format of earlier releases"):
        settings = layered_settings(settings_file)
    assert (settings.recipe.name, settings.run.seed) == ("ch4-team", 3)
    with pytest.warns(FutureWarning, match=r"settings format of earlier releases .*\(base: <recipe>"):
        assert TrainSettings.from_dict({"preset": "ch4-team"}).recipe.to_dict() == load_recipe("ch4-team").to_dict()


def test_the_setups_module_is_the_recipes_module() -> None:
    from sb3_formation.experiment import recipes

    with pytest.warns(FutureWarning, match=r"experiment\.setups\.load_setup is deprecated .*experiment\.recipes\.load_recipe"):
        from sb3_formation.experiment.setups import load_setup
    assert load_setup is recipes.load_recipe
    with pytest.warns(FutureWarning, match=r"experiment\.setups\.SetUp is deprecated"):
        from sb3_formation.experiment.setups import SetUp
    assert SetUp is recipes.Recipe
