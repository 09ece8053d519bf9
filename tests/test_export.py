"""ONNX export (``sb3_formation.sb3.onnx_export``) and the torch-free runtime (``sb3_formation.runtime``): the graph
acts as the torch policy does, carries a recurrent state, plays the same episodes, and refuses bad input in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from gymnasium import spaces

from sb3_formation.cli import main
from sb3_formation.controllers import ShrinkingController
from sb3_formation.controllers.residual import ResidualPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.observations import observation_fields
from sb3_formation.env.scenes import BENCHMARK_SCENES, SCENES
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.pretrained import ONNX_FILE, PRETRAINED_DIR, load_pretrained, pretrained_names
from sb3_formation.experiment.targets import Target, load_policy
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.runtime.onnx_policy import METADATA_PREFIX
from sb3_formation.sb3.onnx_export import export_onnx
from sb3_formation.sb3.policies import FormationPolicy
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy
from sb3_formation.sb3.trained import TrainedPolicy

SHIPPED = pretrained_names()
#: The issue's bound on |onnxruntime - torch| over every action component.
TOLERANCE = 1e-5


def shipped_onnx(name: str) -> OnnxPolicy:
    return OnnxPolicy(PRETRAINED_DIR / name / ONNX_FILE, threads=1)


def played_observations(policy: ResidualPolicy | TrainedPolicy, rows: int, seed: int = 0) -> np.ndarray:
    """At least ``rows`` observations (whole teams) of stage-3 episodes of 16 teams, acted in by ``policy`` with uniform
    noise on half the steps (so that the states spread beyond the policy's own path)."""
    config = policy.config.replace(stage=3)
    rows = -(-rows // config.n_agents) * config.n_agents
    engine = FormationEngine([config] * 16)
    observations = np.concatenate([engine.reset(team, seed=seed + team) for team in range(16)])
    rng, seen = np.random.default_rng(seed), []
    while sum(len(block) for block in seen) < rows:
        seen.append(observations)
        actions, _ = policy.predict(observations)
        if len(seen) % 2:
            actions = np.clip(actions + rng.uniform(-0.5, 0.5, actions.shape), -1, 1)
        observations = engine.step(actions.astype(np.float64)).observations
    return np.concatenate(seen)[:rows]


def normalizer_state(config: FormationConfig, seed: int, center: bool) -> dict[str, np.ndarray]:
    """Frozen normaliser statistics of the task's layout with spread variances (and means, for ``center``)."""
    rng = np.random.default_rng(seed)
    mask = np.concatenate([np.full(field.size, field.binary) for field in observation_fields(config)])
    return {
        "mean": rng.normal(0, 1, mask.size),
        "var": rng.uniform(0.01, 4.0, mask.size),
        "count": np.array(1000.0),
        "agent_obs_dim": np.array(mask.size),
        "binary_mask": mask,
        "epsilon": np.array(1e-8),
        "clip_obs": np.array(5.0),
        "center": np.array(center),
    }


def untrained(config: FormationConfig, recurrent: str | None, seed: int, center: bool = False) -> TrainedPolicy:
    """A freshly initialised policy whose action layer is scaled up (SB3's 0.01 gain makes near-zero actions, which
    would hide any difference), with spread normaliser statistics."""
    torch.manual_seed(seed)
    size = sum(field.size for field in observation_fields(config))
    box, actions = spaces.Box(-np.inf, np.inf, (size,), np.float32), spaces.Box(-1, 1, (2,), np.float32)
    if recurrent is None:
        policy = FormationPolicy(box, actions, lambda _: 3e-4, net_arch=dict(pi=[64, 32], vf=[32]))
    else:
        arch = dict(pi=[64], pi_recurrent=32, vf=[16], vf_recurrent=16, vf_after=[])
        policy = RecurrentFormationPolicy(box, actions, lambda _: 3e-4, net_arch=arch, cell=recurrent)
    with torch.no_grad():
        policy.action_net.weight.mul_(300.0)
    return TrainedPolicy(policy, config, normalizer_state(config, seed, center))


@pytest.mark.parametrize("name", SHIPPED)
def test_onnxruntime_acts_as_torch_on_10000_observations_of_each_shipped_policy(name: str) -> None:
    torch_policy, onnx_policy = load_pretrained(name), shipped_onnx(name)
    observations = played_observations(torch_policy, 10_000)
    expected, _ = torch_policy.predict(observations)
    actions, _ = onnx_policy.predict(observations)
    assert actions.shape == expected.shape and len(actions) >= 10_000 and actions.dtype == np.float32
    assert np.abs(actions - expected).max() <= TOLERANCE
    # the graph's own output, before the controller's action is added (a clip at the box's edge cannot hide it); a
    # recurrent graph's memory and messages heard are zeros, as at an episode's first step
    feeds = {"observation": observations} | {
        graph_input.name: np.zeros([len(observations) if size == "batch" else size for size in graph_input.shape], np.float32)
        for graph_input in onnx_policy.session.get_inputs()[1:]
    }
    correction = onnx_policy.session.run(None, feeds)[0]
    assert np.abs(correction - torch_policy.correction.predict(observations)[0]).max() <= TOLERANCE
    assert np.abs(correction).max() > 0.1  # the graph does act


@pytest.mark.parametrize("center", [False, True])
def test_a_feed_forward_policy_exports_with_its_normaliser_folded_in(center: bool, tmp_path: Path) -> None:
    config = FormationConfig.task("ch5-bearing")
    trained = untrained(config, None, seed=3, center=center)
    runtime = OnnxPolicy(export_onnx(trained, tmp_path / "mlp.onnx"), threads=1)
    assert runtime.metadata.output_names == ["action"] and runtime.residual is None
    observations = played_observations(trained, 2000, seed=5)
    expected, _ = trained.predict(observations)
    actions, state = runtime.predict(observations)
    assert state is None and np.abs(actions - expected).max() <= TOLERANCE
    assert np.abs(expected).max() > 0.5  # the normalised inputs reach the actions
    one, _ = runtime.predict(observations[7])  # one agent's observation: one action
    assert one.shape == (2,) and np.abs(one - expected[7]).max() <= TOLERANCE


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_a_recurrent_export_carries_its_state_over_a_100_step_episode(cell: str, tmp_path: Path) -> None:
    config = FormationConfig.task("ch5-bearing", stage=3)
    trained = untrained(config, cell, seed=4, center=True)
    runtime = OnnxPolicy(export_onnx(trained, tmp_path / f"{cell}.onnx"), threads=1)
    parts = ("hidden",) if cell == "gru" else ("hidden", "cell")
    assert runtime.metadata.input_names == ["observation", *(f"{part}_in" for part in parts)]
    assert runtime.metadata.output_names == ["action", *(f"{part}_out" for part in parts)]
    engine = FormationEngine([config])
    observations = engine.reset(0, seed=11)
    starts = np.ones(config.n_agents, dtype=bool)
    torch_state = onnx_state = None
    forgetful_gap = 0.0
    for _ in range(100):
        expected, torch_state = trained.predict(observations, torch_state, starts)
        actions, onnx_state = runtime.predict(observations, onnx_state, starts)
        assert np.abs(actions - expected).max() <= TOLERANCE
        assert all(np.abs(mine - theirs).max() <= TOLERANCE for mine, theirs in zip(onnx_state, torch_state))
        forgetful, _ = runtime.predict(observations, None, starts)  # the same step from a zero state
        forgetful_gap = max(forgetful_gap, float(np.abs(forgetful - actions).max()))
        starts[:] = False
        step = engine.step(expected.astype(np.float64))
        assert not (step.terminated[0] or step.truncated[0])
        observations = step.observations
    assert forgetful_gap > 1e-2  # the state matters, so carrying it is what made the actions agree
    assert [array.shape for array in onnx_state] == [(1, config.n_agents, 32)] * len(parts)


def test_a_residual_on_a_controller_with_memory_carries_the_memory_beside_the_graph(tmp_path: Path) -> None:
    """A correction of controller:shrinking: the runtime's state is (graph state, controller memory); fed back, it acts
    as the torch residual policy through a passage episode, episode starts reset it, and without it the actions differ."""
    config = FormationConfig.task("ch5-bearing", stage=3).replace(scenes="passage")
    residual = ResidualPolicy(ShrinkingController(config), untrained(config, None, seed=6), 0.3)
    runtime = OnnxPolicy(export_onnx(residual, tmp_path / "shrinking.onnx"), threads=1)
    assert isinstance(runtime.residual.controller, ShrinkingController) and runtime.residual.scale == 0.3
    engine = FormationEngine([config])
    observations = engine.reset(0, seed=2)
    starts = np.ones(config.n_agents, dtype=bool)
    torch_state = onnx_state = None
    forgetful_gap = 0.0
    for step_index in range(300):
        if step_index == 150:  # a new episode in the same rows: both reset the memory
            observations, starts[:] = engine.reset(0, seed=3), True
        expected, torch_state = residual.predict(observations, torch_state, starts)
        actions, onnx_state = runtime.predict(observations, onnx_state, starts)
        assert np.abs(actions - expected).max() <= TOLERANCE
        np.testing.assert_array_equal(onnx_state[1], torch_state[1])  # the same memory, computed in numpy by both
        forgetful, _ = runtime.predict(observations, None, starts)
        forgetful_gap = max(forgetful_gap, float(np.abs(forgetful - actions).max()))
        starts[:] = False
        observations = engine.step(expected.astype(np.float64)).observations
    assert onnx_state[0] is None  # a feed-forward graph has no state of its own
    assert forgetful_gap > 1e-2


@pytest.mark.parametrize("name", SHIPPED)
def test_each_exported_shipped_policy_has_the_torch_policys_successes_on_20_stage_3_episodes(name: str) -> None:
    """Both play the 20 episodes of the policy's scenes at once (20 teams); about 8 s a policy, most of it torch's. A
    policy of scenes with moving obstacles plays the static families instead: among movers the two runtimes' last-bit
    differences change which agent a walker meets, and an episode's outcome with it (1 of 20 measured)."""
    policy = load_pretrained(name)
    moving = SCENES[policy.config.scenes].obstacle_speed(policy.config) > 0
    protocol = dict(episodes=20, stage=3, seed=0, n_envs=20, record=0, env_overrides={"scenes": "mixed"} if moving else None)
    expected = evaluate(policy, **protocol).episodes
    played = evaluate(shipped_onnx(name), **protocol).episodes
    assert [row["success"] for row in played] == [row["success"] for row in expected]


def test_the_runtime_acts_in_a_process_that_never_loads_torch_or_sb3() -> None:
    code = (
        "import sys, numpy as np\n"
        "from sb3_formation.runtime import OnnxPolicy\n"
        f"policy = OnnxPolicy({str(PRETRAINED_DIR / 'ch5-bearing' / ONNX_FILE)!r})\n"
        "actions = policy.agent_step(np.zeros((1, policy.observation_dim), np.float32), np.array([2])).action\n"
        "assert actions.shape == (1, 2)\n"
        "print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_the_metadata_hold_the_task_layout_version_and_opset() -> None:
    model = onnx.load(str(PRETRAINED_DIR / "ch4-team" / ONNX_FILE))
    properties = {entry.key: entry.value for entry in model.metadata_props}
    torch_policy = load_pretrained("ch4-team")
    assert FormationConfig.from_dict(json.loads(properties[METADATA_PREFIX + "config"])) == torch_policy.config
    layout = json.loads(properties[METADATA_PREFIX + "observation_layout"])
    assert layout[0] == {"name": "lidar_obstacles", "start": 0, "stop": torch_policy.config.lidar_rays, "binary": False}
    assert sum(field["stop"] - field["start"] for field in layout) == shipped_onnx("ch4-team").observation_dim
    assert json.loads(properties[METADATA_PREFIX + "package_version"]) == "0.1.0"
    assert json.loads(properties[METADATA_PREFIX + "opset"]) == 18 == model.opset_import[0].version
    residual = json.loads(properties[METADATA_PREFIX + "residual"])
    assert residual["controller"] == "classical" and residual["scale"] == 0.3
    assert json.loads(properties[METADATA_PREFIX + "recurrent"]) is None
    assert json.loads(properties[METADATA_PREFIX + "team_sizes"]) == [3]


def test_a_robot_acts_for_its_own_agent_with_its_index() -> None:
    """The residual controller needs the agent's index: one robot's row with index i acts as row i of its team."""
    policy = shipped_onnx("ch5-bearing")
    team = played_observations(load_pretrained("ch5-bearing"), 6, seed=2)
    together, _ = policy.predict(team)
    for agent in range(6):
        alone = policy.agent_step(team[agent], np.array([agent])).action
        assert np.array_equal(alone[0], together[agent])


def test_a_policy_trained_on_several_team_sizes_fits_any_size_and_others_refuse() -> None:
    mixed, single = shipped_onnx("mixed-ch5-bearing"), shipped_onnx("ch5-bearing")
    fitted = mixed.fit(mixed.config.replace(n_agents=4))
    assert fitted.config.n_agents == 4 and fitted.residual.controller.config.n_agents == 4 and mixed.config.n_agents != 4
    with pytest.raises(ValueError, match="n_agents=6 in the model, 4 in the env"):
        single.fit(single.config.replace(n_agents=4))
    with pytest.raises(ValueError, match="lidar_rays"):
        single.fit(single.config.replace(lidar_rays=12))


def test_export_and_evaluate_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # compare writes the shipped policy's evaluation under ./evaluations
    out = tmp_path / "policy.onnx"
    for opset in ("1", "17", "26", "99"):  # one line, nothing written (torch would fall back, or write 18 silently)
        assert main(["export", "pretrained:ch4-individual", "--onnx", str(out), "--opset", opset]) == 2
        assert (
            capsys.readouterr().err
            == f"sb3-formation: error: opset must be 18-25 (what torch's exporter writes), got {opset}\n"
        )
        assert not out.exists()
    assert main(["export", "pretrained:ch4-individual", "--onnx", str(out), "--opset", "21"]) == 0
    assert "opset 21" in capsys.readouterr().out
    assert main(["export", "pretrained:ch4-individual", "--onnx", str(out)]) == 0
    assert "opset 18" in capsys.readouterr().out
    assert isinstance(load_policy(f"onnx:{out}"), OnnxPolicy) and isinstance(load_policy(out), OnnxPolicy)
    assert Target.parse(out).evaluation_folder() == tmp_path / "eval_policy"  # beside, not over, the model's own evaluation
    assert main(["evaluate", f"onnx:{out}", "--episodes", "2", "--n-envs", "2", "--no-progress", "--trajectories", "0"]) == 0
    summary = json.loads((tmp_path / "eval_policy" / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["model"]["file"] == str(out)
    # render, compare (on a scene family) and benchmark take the exported file as any target
    assert main(["render", str(out), "--max-steps", "5", "--out", str(tmp_path / "v.gif")]) == 0
    assert (tmp_path / "v.gif").stat().st_size > 0
    compare = ["compare", f"onnx:{out}", "pretrained:ch4-individual", "--scenes", "passage", "--episodes", "2"]
    assert main([*compare, "--n-envs", "2", "--no-progress", "--out", str(tmp_path / "compare")]) == 0
    rows = [line.split(" | ")[0] for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    assert rows[1:] == ["| policy", "| pretrained:ch4-individual"]  # the file's name labels it
    assert json.loads((tmp_path / "eval_policy-passage" / "summary.json").read_text())["scenes"] == "passage"
    assert (tmp_path / "evaluations" / "pretrained-ch4-individual_residual-ch4-individual-passage").is_dir()
    benchmark = ["benchmark", f"onnx:{out}", "--episodes", "1", "--workers", "1", "--no-progress"]
    assert main([*benchmark, "--labels", "exported", "--out", str(tmp_path / "bench")]) == 0
    rows = json.loads((tmp_path / "bench" / "benchmark.json").read_text())["rows"]
    assert [row["target"] for row in rows] == ["exported"] * len(BENCHMARK_SCENES) and rows[0]["n_agents"] == 3


def bad_inputs(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """Files that are not exported policies, with what the one-line error must say."""
    damaged = tmp_path / "damaged.onnx"
    damaged.write_bytes((PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE).read_bytes()[:5000])
    foreign = tmp_path / "foreign.onnx"
    model = onnx.load(str(PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE))
    del model.metadata_props[:]
    onnx.save_model(model, str(foreign))
    return {
        "missing": (tmp_path / "missing.onnx", "no exported policy at"),
        "damaged": (damaged, "is not a readable ONNX model"),
        "foreign": (foreign, "is not a policy exported by sb3-formation: its metadata lack sb3_formation.format"),
    }


@pytest.mark.parametrize("case", ["missing", "damaged", "foreign"])
def test_a_file_that_is_not_an_exported_policy_is_refused_in_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, message = bad_inputs(tmp_path)[case]
    with pytest.raises((FileNotFoundError, ValueError), match=message):
        OnnxPolicy(path)
    assert main(["evaluate", str(path), "--episodes", "1", "--no-progress"]) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and message in error and str(path) in error


def test_wrong_observations_states_or_stochastic_acting_are_refused(tmp_path: Path) -> None:
    policy = shipped_onnx("ch5-bearing")
    size = policy.observation_dim
    with pytest.raises(ValueError, match=rf"reads observations of {size} features per agent .* shape \(6, {size - 1}\)"):
        policy.predict(np.zeros((6, size - 1), np.float32))
    with pytest.raises(ValueError, match="acts deterministically only"):
        policy.predict(np.zeros((6, size), np.float32), deterministic=False)
    recurrent = OnnxPolicy(export_onnx(untrained(policy.config, "gru", seed=1), tmp_path / "gru.onnx"))
    with pytest.raises(ValueError, match=r"needs a state of 1 arrays of shape \(1, 6, 32\) \(hidden\), got \[\(1, 3, 32\)\]"):
        recurrent.predict(np.zeros((6, size), np.float32), (np.zeros((1, 3, 32), np.float32),))


def test_export_refuses_what_it_cannot_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", "controller:classical", "--onnx", str(tmp_path / "c.onnx")]) == 2
    error = capsys.readouterr().err.strip()
    assert error == (
        "sb3-formation: error: only trained policies can be exported to ONNX, not ClassicalController "
        "(controllers are numpy code)"
    )
    assert not (tmp_path / "c.onnx").exists()


@pytest.mark.parametrize("module", ["onnxruntime", "onnx"])
def test_a_missing_runtime_package_is_named_with_the_extra_that_installs_it(
    module: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # import <module> then raises ImportError
    target = str(PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE)
    assert main(["evaluate", target, "--episodes", "1", "--out", str(tmp_path / "eval"), "--no-progress"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"sb3-formation: error: running an exported policy needs {module}: pip install 'sb3-formation[runtime]'"
    )
