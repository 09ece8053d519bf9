"""The ``sb3-formation`` command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.cli import main
from sb3_formation.rollout import random_policy, run_episode


def test_rollout_prints_episodes_and_saves_the_final_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "frames" / "final.png"
    arguments = ["rollout", "--preset", "ch4-team", "--episodes", "2", "--max-steps", "40", "--seed", "3", "--json"]
    assert main([*arguments, "--out", str(tmp_path / "first.png")]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [line["episode"] for line in lines] == [0, 1]
    assert all(line["length"] == 40 and line["success"] is False for line in lines)
    assert main(["rollout", "--episodes", "1", "--max-steps", "10", "--out", str(out)]) == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (600, 900, 3) and image.std() > 5


def test_rollout_summary_matches_a_manual_episode() -> None:
    config = FormationConfig.preset("ch5-angle", stage=2, max_steps=25)
    env = FormationEnv(config)
    summary = run_episode(env, random_policy(env, seed=1), seed=4)
    twin = FormationEnv(config)
    observations, _ = twin.reset(seed=4)
    rng = np.random.default_rng(1)
    total, angles = 0.0, []
    while twin.agents:
        observations, rewards, _, _, infos = twin.step({agent: rng.uniform(-1.0, 1.0, 2) for agent in observations})
        total += sum(rewards.values()) / len(rewards)
        angles += [info["angle_error_deg"] for info in infos.values()]
    assert summary["length"] == 25 and summary["stage"] == 2
    assert summary["return"] == pytest.approx(total)
    assert summary["angle_error_deg"] == pytest.approx(np.mean(angles))
    assert summary["final_goal_distance"] == pytest.approx(twin.goal_distance)


def test_bad_input_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rollout", "--agents", "2", "--max-steps", "5"]) == 2
    assert "n_agents" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["rollout", "--bogus"])
    assert exit_info.value.code == 2
    assert "--bogus" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["rollout", "--preset", "ch9"])
