"""Policies whose agents send messages to their ring neighbours (``RecurrentFormationPolicy(message_size=M)``): an
update replays the teams' rollouts exactly, an agent hears only its two ring neighbours and one step late, the ONNX
graph carries messages and memory over whole episodes as torch does, and bad settings are one-line errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import CallbackList
from stable_baselines3.common.vec_env import DummyVecEnv
from test_export import TOLERANCE, normalizer_state

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.geometry import ring_rows
from sb3_formation.env.observations import observation_fields
from sb3_formation.experiment.sections import PolicySection
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.sb3.onnx_export import export_onnx
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy, RecurrentFormationPPO
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.sb3.vec_env import make_formation_vec_env

SMALL = dict(pi=[32], pi_recurrent=16, vf=[32], vf_recurrent=16, vf_after=[16])


def test_ring_rows_name_each_rows_neighbours_within_its_team() -> None:
    # teams of 3 and 4 stacked: rows 0-2 and 3-6; row 3 (agent 0 of the second team) hears rows 6 and 4
    expected = [[2, 1], [0, 2], [1, 0], [6, 4], [3, 5], [4, 6], [5, 3]]
    np.testing.assert_array_equal(ring_rows([3, 4]), expected)


def rollout(memory: bool, cell: str) -> RecurrentFormationPPO:
    """A PPO with messages after one rollout of 48 steps in teams of 4, 3 and 5 whose episodes last 20 steps, its
    sequences cut every 7 steps."""
    env = make_formation_vec_env("ch5-bearing", n_envs=3, seed=0, stage=1, max_steps=20, team_sizes=[4, 3, 5])
    model = RecurrentFormationPPO(
        env=env,
        n_steps=48,
        batch_size=96,
        n_epochs=1,
        seed=0,
        max_sequence_length=7,
        policy_kwargs=dict(message_size=3, memory=memory, cell=cell, net_arch=SMALL),
    )
    model._setup_learn(48, None)
    callback = CallbackList([])
    callback.init_callback(model)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, 48)
    return model


@pytest.mark.parametrize(("memory", "cell"), [(True, "gru"), (True, "lstm"), (False, "gru")])
def test_an_update_replays_every_teams_rollout_with_its_messages_exactly(memory: bool, cell: str) -> None:
    """Replayed from the stored states, whole teams at a time, the sequences give the log-probabilities and values of
    the rollout (so each column heard the neighbours it heard then), and a receiver's loss reaches the sender."""
    model = rollout(memory, cell)
    buffer, policy = model.rollout_buffer, model.policy
    assert buffer.episode_starts[1:].sum() == 2 * 12  # every slot starts episodes at steps 20 and 40
    columns = 0
    for batch in buffer.sequence_batches(96):
        neighbours = batch.neighbours.numpy()
        assert neighbours.shape == (batch.observations.shape[1], 2)
        # whole teams: every column's succeeding neighbour has it as its preceding one, and every ring closes
        np.testing.assert_array_equal(neighbours[neighbours[:, 1], 0], np.arange(len(neighbours)))
        with th.no_grad():
            values, log_prob, _ = policy.evaluate_sequences(batch.observations, batch.actions, batch.states, batch.neighbours)
        assert (log_prob - batch.old_log_prob)[batch.mask].abs().max() <= 1e-5
        assert (values - batch.old_values)[batch.mask].abs().max() <= 1e-5
        columns += batch.observations.shape[1]
    assert columns == 12 * 9  # 12 slots, each cut at steps 0, 7, 14, 20, 21, 28, 35, 40 and 42
    batch = next(buffer.sequence_batches(96))
    policy.zero_grad()
    _, log_prob, _ = policy.evaluate_sequences(batch.observations, batch.actions, batch.states, batch.neighbours)
    log_prob[1:][batch.mask[1:]].sum().backward()  # actions after the first step hear messages computed in the replay
    assert policy.message_net.weight.grad.abs().sum() > 0


def untrained(config: FormationConfig, memory: bool, seed: int, action_gain: float = 30.0) -> TrainedPolicy:
    """A fresh policy with messages of 4 values whose action and message layers are scaled up (SB3's 0.01 gain makes
    near-zero actions, which would hide any difference), with spread normaliser statistics."""
    th.manual_seed(seed)
    size = sum(field.size for field in observation_fields(config))
    box, actions = spaces.Box(-np.inf, np.inf, (size,), np.float32), spaces.Box(-1, 1, (2,), np.float32)
    arch = dict(pi=[64], pi_recurrent=32, vf=[16], vf_recurrent=16, vf_after=[])
    policy = RecurrentFormationPolicy(box, actions, lambda _: 3e-4, net_arch=arch, message_size=4, memory=memory)
    with th.no_grad():
        policy.action_net.weight.mul_(action_gain)
        policy.message_net.weight.mul_(3.0)
    return TrainedPolicy(policy, config, normalizer_state(config, seed, center=True))


@pytest.mark.parametrize("memory", [True, False])
def test_an_agent_hears_only_its_ring_neighbours_and_one_step_late(memory: bool) -> None:
    """Agent 3's observation changed at step 0 of a team of 6 (two teams played at once, the second untouched): at step
    0 only agent 3 acts otherwise; at step 1 agents 2 and 4 (its messages) and, with memory, 3 itself; at step 2 also
    1 and 5; agent 0, three hops away, only at step 3. The other team never changes."""
    config = FormationConfig.task("ch5-bearing", stage=3)
    trained = untrained(config, memory, seed=1)
    engine = FormationEngine([config] * 2)
    observations = [np.concatenate([engine.reset(team, seed=team) for team in range(2)])]
    for _ in range(3):
        actions, _ = trained.predict(observations[-1])
        observations.append(engine.step(actions.astype(np.float64)).observations)
    changed = [rows.copy() for rows in observations]
    changed[0][3] += np.random.default_rng(0).normal(0.0, 0.5, changed[0][3].shape).astype(np.float32)
    starts, plain_state, changed_state = np.ones(12, bool), None, None
    moved = []
    for plain_rows, changed_rows in zip(observations, changed):
        plain, plain_state = trained.predict(plain_rows, plain_state, starts)
        other, changed_state = trained.predict(changed_rows, changed_state, starts)
        moved.append(set(np.flatnonzero(np.abs(other - plain).max(axis=1) > 1e-6)))
        starts[:] = False
    expected = [{3}, {2, 3, 4} if memory else {2, 4}, {1, 2, 3, 4, 5} if memory else {1, 3, 5}]
    assert moved[:3] == expected
    assert 0 in moved[3] and not moved[3] & set(range(6, 12))


@pytest.mark.parametrize("memory", [True, False])
def test_the_onnx_graph_of_a_communicating_policy_acts_as_torch_over_whole_episodes(memory: bool, tmp_path: Path) -> None:
    """Two teams through whole 150-step episodes (time-outs), then new episodes in the same rows: the runtime's actions
    and messages agree with torch's within 1e-5; a robot that hosts one agent and gets its neighbours' messages acts
    as that agent's row of its team."""
    config = FormationConfig.task("ch5-bearing", stage=3, max_steps=150)
    trained = untrained(config, memory, seed=2, action_gain=300.0)
    runtime = OnnxPolicy(export_onnx(trained, tmp_path / "messages.onnx"), threads=1)
    parts = ["hidden"] if memory else []
    assert runtime.metadata.input_names == ["observation", *(f"{part}_in" for part in parts), "message_in"]
    assert runtime.metadata.output_names == ["action", *(f"{part}_out" for part in parts), "message_out"]
    assert runtime.metadata.message_size == 4
    engine = FormationEngine([config] * 2)
    torch_state: Any = None
    onnx_state: Any = None
    robot_states: list[Any] = [None] * 6
    for episode in range(2):
        observations = np.concatenate([engine.reset(team, seed=10 * episode + team) for team in range(2)])
        starts = np.ones(12, dtype=bool)
        for step_index in range(config.max_steps):
            sent = None if onnx_state is None else onnx_state[1] * (1.0 - starts[:, None])
            expected, torch_state = trained.predict(observations, torch_state, starts)
            actions, onnx_state = runtime.predict(observations, onnx_state, starts)
            assert np.abs(actions - expected).max() <= TOLERANCE
            assert np.abs(onnx_state[1] - torch_state[-1]).max() <= TOLERANCE  # the messages sent
            if step_index % 50 == 0:  # each robot of team 0 alone, with what its neighbours sent
                for agent in range(6):
                    received = None if sent is None else sent[ring_rows([6])[agent]][None]
                    step = runtime.agent_step(
                        observations[agent], np.array([agent]), robot_states[agent], starts[:1], received
                    )
                    assert np.abs(step.action[0] - actions[agent]).max() <= TOLERANCE
                    assert np.abs(step.message[0] - onnx_state[1][agent]).max() <= TOLERANCE
            for agent in range(6):
                robot_states[agent] = None if onnx_state[0] is None else (onnx_state[0][0][:, agent : agent + 1],)
            starts[:] = False
            stepped = engine.step(expected.astype(np.float64))
            observations = stepped.observations
        assert stepped.truncated.all()
    assert np.abs(onnx_state[1]).max() > 0.1  # the messages are not all zeros


def test_bad_message_settings_are_one_line_errors(tmp_path: Path) -> None:
    config = FormationConfig.task("ch5-bearing")
    size = sum(field.size for field in observation_fields(config))
    box, actions = spaces.Box(-np.inf, np.inf, (size,), np.float32), spaces.Box(-1, 1, (2,), np.float32)
    for bad in (-1, 2.5, True, 10_000):
        with pytest.raises(ValueError, match="message_size must be an integer in"):
            RecurrentFormationPolicy(box, actions, lambda _: 3e-4, message_size=bad)
    with pytest.raises(ValueError, match="memory must be true or false"):
        RecurrentFormationPolicy(box, actions, lambda _: 3e-4, memory="yes")
    with pytest.raises(ValueError, match="message_size 4 applies to recurrent policies only"):
        PolicySection(message_size=4)
    with pytest.raises(ValueError, match="memory False applies to recurrent policies only"):
        PolicySection(memory=False)
    with pytest.raises(ValueError, match="message_size must be an integer in"):
        PolicySection(recurrent=True, message_size=-2)
    policy = RecurrentFormationPolicy(box, actions, lambda _: 3e-4, message_size=2, net_arch=SMALL)
    with pytest.raises(ValueError, match="needs each row's ring neighbours"):
        policy.predict(np.zeros((6, size), np.float32))
    runtime = OnnxPolicy(export_onnx(untrained(config, True, seed=5), tmp_path / "talk.onnx"), threads=1)
    row = np.zeros((1, size), np.float32)
    with pytest.raises(ValueError, match=r"needs received messages of shape \(1, 2, 4\)"):
        runtime.agent_step(row, np.array([0]), received=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="NaN or infinite"):
        runtime.agent_step(row, np.array([0]), received=np.full((1, 2, 4), np.nan))
    pendulum = DummyVecEnv([lambda: gymnasium.make("Pendulum-v1")])
    with pytest.raises(ValueError, match="trains on the package's FormationVecEnv"):
        RecurrentFormationPPO(env=pendulum, policy_kwargs=dict(message_size=2, net_arch=SMALL))
