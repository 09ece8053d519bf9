"""Tests of the recurrent PPO (:mod:`sb3_formation.sb3.recurrent`): sequence cutting, sequence minibatches, the GRU/LSTM
policy against a float64 NumPy re-implementation of its cells, rollouts replayed step by step, save/load, validation.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn

from sb3_formation.sb3.recurrent import (
    DEFAULT_MAX_SEQUENCE_LENGTH,
    RecurrentFormationPolicy,
    RecurrentFormationPPO,
    RecurrentRolloutBuffer,
    RecurrentStates,
    sequence_layout,
)

CELLS = ("gru", "lstm")
NET_ARCH = {"pi": [8], "pi_recurrent": 6, "vf": [8], "vf_recurrent": 5, "vf_after": [4]}
PI_HIDDEN, VF_HIDDEN = 6, 5
OBS_DIM = 3
LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


# ---------------------------------------------------------------------------------------------------------------------
# helpers: a float64 NumPy re-implementation of the policy, hand-made environments


def _np(tensor: th.Tensor) -> np.ndarray:
    return tensor.detach().cpu().double().numpy()


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class Reference:
    """The policy's actor and critic recomputed for one slot in float64 NumPy (GRU/LSTM equations written out).

    A state is a tuple of ``(hidden,)`` arrays: ``(h,)`` for a GRU, ``(h, c)`` for an LSTM. Dense layers use tanh.
    """

    def __init__(self, policy: RecurrentFormationPolicy) -> None:
        assert policy.activation_fn is nn.Tanh
        self.cell, self.sigma, self.scale = policy.cell, policy.sigma, policy.action_scale
        self.actor, self.critic = self._head(policy.actor), self._head(policy.critic)
        self.action_w, self.action_b = _np(policy.action_net.weight), _np(policy.action_net.bias)
        self.value_w, self.value_b = _np(policy.value_net.weight), _np(policy.value_net.bias)

    @staticmethod
    def _head(head: nn.Module) -> dict[str, Any]:
        def dense(sequential: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
            return [(_np(layer.weight), _np(layer.bias)) for layer in sequential if isinstance(layer, nn.Linear)]

        rnn = head.rnn
        return {
            "before": dense(head.before),
            "after": dense(head.after),
            "w_ih": _np(rnn.weight_ih_l0),
            "w_hh": _np(rnn.weight_hh_l0),
            "b_ih": _np(rnn.bias_ih_l0),
            "b_hh": _np(rnn.bias_hh_l0),
            "hidden": rnn.hidden_size,
        }

    def zeros(self, head: str) -> tuple[np.ndarray, ...]:
        hidden = (self.actor if head == "pi" else self.critic)["hidden"]
        return tuple(np.zeros(hidden) for _ in range(1 if self.cell == "gru" else 2))

    def _step(self, head: dict[str, Any], obs: np.ndarray, state: tuple[np.ndarray, ...]):
        x = np.asarray(obs, dtype=np.float64)
        for weight, bias in head["before"]:
            x = np.tanh(weight @ x + bias)
        size, h = head["hidden"], state[0]
        gi = head["w_ih"] @ x + head["b_ih"]
        gh = head["w_hh"] @ h + head["b_hh"]
        if self.cell == "gru":  # gates r, z, n (PyTorch's order)
            r = _sigmoid(gi[:size] + gh[:size])
            z = _sigmoid(gi[size : 2 * size] + gh[size : 2 * size])
            n = np.tanh(gi[2 * size :] + r * gh[2 * size :])
            h = (1 - z) * n + z * h
            new_state: tuple[np.ndarray, ...] = (h,)
        else:  # gates i, f, g, o
            g = gi + gh
            i, f = _sigmoid(g[:size]), _sigmoid(g[size : 2 * size])
            cand, o = np.tanh(g[2 * size : 3 * size]), _sigmoid(g[3 * size :])
            c = f * state[1] + i * cand
            h = o * np.tanh(c)
            new_state = (h, c)
        y = h
        for weight, bias in head["after"]:
            y = np.tanh(weight @ y + bias)
        return y, new_state

    def actor_step(self, obs: np.ndarray, state: tuple[np.ndarray, ...]) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Action mean ``action_scale * tanh(W y + b)`` and the new actor state."""
        y, state = self._step(self.actor, obs, state)
        return self.scale * np.tanh(self.action_w @ y + self.action_b), state

    def critic_step(self, obs: np.ndarray, state: tuple[np.ndarray, ...]) -> tuple[float, tuple[np.ndarray, ...]]:
        """Value and the new critic state."""
        y, state = self._step(self.critic, obs, state)
        return float((self.value_w @ y + self.value_b)[0]), state

    def log_prob(self, mean: np.ndarray, action: np.ndarray) -> float:
        """Diagonal Gaussian log-density of ``action`` with std ``sigma``."""
        z = (np.asarray(action, dtype=np.float64) - mean) / self.sigma
        return float(np.sum(-0.5 * z**2 - math.log(self.sigma) - LOG_SQRT_2PI))


def slot_state(states: tuple[th.Tensor, ...], slot: int) -> tuple[np.ndarray, ...]:
    """One slot's state of a batched ``(1, n, hidden)`` cell state, as float64 arrays."""
    return tuple(_np(tensor[0, slot]) for tensor in states)


def randomize(policy: RecurrentFormationPolicy, seed: int, scale: float = 0.6) -> None:
    """Replace every trainable weight with N(0, scale^2) noise (non-zero biases, saturating tanh)."""
    generator = th.Generator().manual_seed(seed)
    with th.no_grad():
        for name, parameter in policy.named_parameters():
            if name != "log_std":
                parameter.copy_(th.randn(parameter.shape, generator=generator) * scale)


def cloned(states: RecurrentStates) -> RecurrentStates:
    return RecurrentStates(tuple(x.clone() for x in states.pi), tuple(x.clone() for x in states.vf), states.messages.clone())


def random_states(policy: RecurrentFormationPolicy, n: int, seed: int) -> RecurrentStates:
    generator = th.Generator().manual_seed(seed)
    count = 1 if policy.cell == "gru" else 2
    return RecurrentStates(
        tuple(th.randn(1, n, PI_HIDDEN, generator=generator) for _ in range(count)),
        tuple(th.randn(1, n, VF_HIDDEN, generator=generator) for _ in range(count)),
        th.zeros(n, 0),
    )


def make_policy(
    cell: str, low: float = -1.0, high: float = 1.0, seed: int = 0, scale: float = 0.6, **kwargs: Any
) -> RecurrentFormationPolicy:
    """A tiny recurrent policy with random weights for ``OBS_DIM`` observations and 2-D actions in ``[low, high]``."""
    policy = RecurrentFormationPolicy(
        spaces.Box(-100.0, 100.0, (OBS_DIM,), np.float32),
        spaces.Box(low, high, (2,), np.float32),
        lambda _: 1e-3,
        net_arch=NET_ARCH,
        cell=cell,
        **kwargs,
    )
    randomize(policy, seed, scale)
    return policy


def step_reward(slot: int, step: int) -> float:
    """Reward of the step that ends at ``step`` (1-based) in slot ``slot``'s env."""
    return slot + 0.25 * step


class CountingEnv(gym.Env):
    """Episodes of ``length`` steps; observation ``(slot, step in episode, episode index)``; ends by time-out if
    ``truncate`` else by termination; reward :func:`step_reward`; actions are ignored."""

    def __init__(self, slot: int, length: int, truncate: bool) -> None:
        self.observation_space = spaces.Box(-100.0, 100.0, (OBS_DIM,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.slot, self.length, self.truncate = slot, length, truncate
        self.step_count, self.episode = 0, -1

    def _obs(self) -> np.ndarray:
        return np.array([self.slot, self.step_count, self.episode], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.step_count, self.episode = 0, self.episode + 1
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.step_count += 1
        end = self.step_count == self.length
        return self._obs(), step_reward(self.slot, self.step_count), end and not self.truncate, end and self.truncate, {}


#: Slot 0: episodes of 3 steps that terminate; slot 1: episodes of 5 steps that time out.
LENGTHS, TRUNCATES = (3, 5), (False, True)


def make_env() -> DummyVecEnv:
    return DummyVecEnv([lambda s=s: CountingEnv(s, LENGTHS[s], TRUNCATES[s]) for s in range(2)])


def make_model(cell: str, env: DummyVecEnv | None = None, **kwargs: Any) -> RecurrentFormationPPO:
    policy_kwargs = {"net_arch": NET_ARCH, "cell": cell, **kwargs.pop("policy_kwargs", {})}
    settings = {"n_steps": 7, "batch_size": 7, "n_epochs": 2, "seed": 0, "device": "cpu", **kwargs}
    return RecurrentFormationPPO(env=env or make_env(), policy_kwargs=policy_kwargs, **settings)


# ---------------------------------------------------------------------------------------------------------------------
# 1. sequence_layout


def test_sequence_layout_hand_example() -> None:
    # T = 5, N = 2: slot 0 starts an episode at t = 2, slot 1 at t = 0
    starts = np.zeros((5, 2))
    starts[2, 0] = starts[0, 1] = 1
    layout = sequence_layout(starts)
    # slot-major steps: slot 0 = indices 0..4, slot 1 = 5..9; sequences [s0 t0-1], [s0 t2-4], [s1 t0-4]
    np.testing.assert_array_equal(layout.sequence, [0, 0, 1, 1, 1, 2, 2, 2, 2, 2])
    np.testing.assert_array_equal(layout.position, [0, 1, 0, 1, 2, 0, 1, 2, 3, 4])
    np.testing.assert_array_equal(layout.lengths, [2, 3, 5])
    np.testing.assert_array_equal(layout.slots, [0, 0, 1])
    np.testing.assert_array_equal(layout.first_steps, [0, 2, 0])
    # at most 2 steps: slot 0 [t0-1], [t2-3], [t4]; slot 1 [t0-1], [t2-3], [t4]
    short = sequence_layout(starts, max_length=2)
    np.testing.assert_array_equal(short.lengths, [2, 2, 1, 2, 2, 1])
    np.testing.assert_array_equal(short.first_steps, [0, 2, 4, 0, 2, 4])
    np.testing.assert_array_equal(short.slots, [0, 0, 0, 1, 1, 1])


def test_sequence_layout_second_hand_example() -> None:
    # T = 4, N = 3: slot 0 never starts; slot 1 starts at t = 1 and t = 3; slot 2 at t = 0 and t = 1
    starts = np.array([[0, 0, 1], [0, 1, 1], [0, 0, 0], [0, 1, 0]], dtype=bool)
    layout = sequence_layout(starts)
    # sequences: s0 [0-3] carried; s1 [0] carried, [1-2], [3]; s2 [0], [1-3]
    np.testing.assert_array_equal(layout.sequence, [0, 0, 0, 0, 1, 2, 2, 3, 4, 5, 5, 5])
    np.testing.assert_array_equal(layout.position, [0, 1, 2, 3, 0, 0, 1, 0, 0, 0, 1, 2])
    np.testing.assert_array_equal(layout.lengths, [4, 1, 2, 1, 1, 3])
    np.testing.assert_array_equal(layout.slots, [0, 1, 1, 1, 2, 2])
    np.testing.assert_array_equal(layout.first_steps, [0, 0, 1, 3, 0, 1])


@pytest.mark.parametrize("max_length", [None, 1, 2, 3])
def test_sequence_layout_random_arrays_never_cross_slots_or_episode_starts(max_length: int | None) -> None:
    rng = np.random.default_rng(1234)
    for _ in range(200):
        steps, slots = int(rng.integers(1, 9)), int(rng.integers(1, 5))
        starts = rng.random((steps, slots)) < rng.choice([0.1, 0.4, 0.9])
        layout = sequence_layout(starts.astype(np.float32), max_length)
        count = len(layout.lengths)
        assert layout.sequence.shape == layout.position.shape == (steps * slots,)
        assert layout.slots.shape == layout.first_steps.shape == (count,)
        members: dict[int, list[tuple[int, int]]] = {s: [] for s in range(count)}
        for slot in range(slots):
            for t in range(steps):
                members[int(layout.sequence[slot * steps + t])].append((t, slot))
        # slot-major numbering: ids 0..count-1 in order of (slot, t)
        np.testing.assert_array_equal(layout.sequence, np.sort(layout.sequence))
        for s, steps_of in members.items():
            times = [t for t, _ in steps_of]
            assert {slot for _, slot in steps_of} == {int(layout.slots[s])}
            assert times == list(range(times[0], times[0] + len(times)))  # consecutive in time
            assert layout.lengths[s] == len(times) and layout.first_steps[s] == times[0]
            assert max_length is None or len(times) <= max_length
            np.testing.assert_array_equal(layout.position[[slot * steps + t for t, slot in steps_of]], range(len(times)))
            slot = int(layout.slots[s])
            assert not starts[times[1:], slot].any()  # only the first step may start an episode
            # cut only at the rollout's start, an episode start or a multiple of max_length
            assert times[0] == 0 or starts[times[0], slot] or (max_length is not None and times[0] % max_length == 0)
        cuts = np.zeros((steps, slots), dtype=bool)
        cuts[:: max_length or steps] = True
        assert count == int((cuts | starts).sum())


# ---------------------------------------------------------------------------------------------------------------------
# 2. RecurrentRolloutBuffer.sequence_batches


def fill_buffer(starts: np.ndarray, cell: str, max_length: int | None = None) -> RecurrentRolloutBuffer:
    """A full buffer whose entries encode (t, slot), with distinctive states per (t, slot) (zeros at episode starts)."""
    steps, slots = starts.shape
    buffer = RecurrentRolloutBuffer(
        steps,
        spaces.Box(-1000.0, 1000.0, (OBS_DIM,), np.float32),
        spaces.Box(-1.0, 1.0, (2,), np.float32),
        device="cpu",
        gae_lambda=0.9,
        gamma=0.8,
        n_envs=slots,
    )
    buffer.max_sequence_length = max_length
    n = np.arange(slots, dtype=np.float32)
    count = 1 if cell == "gru" else 2
    for t in range(steps):
        obs = np.stack([n, np.full(slots, t), 100 + 10 * n + t], axis=1).astype(np.float32)
        actions = np.stack([np.full(slots, t + 0.5), -n], axis=1).astype(np.float32)
        values = th.as_tensor(0.1 * (t + 1) * (n + 1)).view(-1, 1)
        log_probs = th.as_tensor(-(t + 10 * n) / 10)
        keep = th.as_tensor(1.0 - starts[t], dtype=th.float32).view(1, -1, 1)
        slot_ids = th.arange(slots).view(1, -1, 1) + 1
        pi = tuple(keep * ((k + 1) * slot_ids + t + 0.01 * th.arange(PI_HIDDEN)) for k in range(count))
        vf = tuple(keep * (-(k + 1) * slot_ids - t - 0.01 * th.arange(VF_HIDDEN)) for k in range(count))
        buffer.add_states(RecurrentStates(tuple(x.float() for x in pi), tuple(x.float() for x in vf), th.zeros(slots, 0)))
        buffer.add(obs, actions, 1 + t + n, starts[t], values, log_probs)
    buffer.compute_returns_and_advantage(last_values=th.linspace(-1, 1, slots), dones=np.arange(slots) % 2 == 1)
    return buffer


def expected_sequences(starts: np.ndarray, max_length: int | None = None) -> set[tuple[int, int, int]]:
    """(slot, first t, length) of each sequence, by a plain loop."""
    steps, slots = starts.shape
    sequences = set()
    for slot in range(slots):
        first = 0
        for t in range(1, steps + 1):
            if t == steps or starts[t, slot] or (max_length is not None and t % max_length == 0):
                sequences.add((slot, first, t - first))
                first = t
    return sequences


def check_batches(buffer: RecurrentRolloutBuffer, batch_size: int, expected: set[tuple[int, int, int]]) -> None:
    steps, slots = buffer.buffer_size, buffer.n_envs
    arrays = {
        "observations": buffer.observations,
        "actions": buffer.actions,
        "old_values": buffer.values,
        "old_log_prob": buffer.log_probs,
        "advantages": buffer.advantages,
        "returns": buffer.returns,
    }
    seen_steps: list[tuple[int, int]] = []
    seen_sequences: list[tuple[int, int, int]] = []
    batches = list(buffer.sequence_batches(batch_size))
    longest = max(length for _, _, length in expected)
    assert len(batches) <= math.ceil(steps * slots / batch_size)
    for batch in batches:
        mask = batch.mask.numpy()
        rows, width = mask.shape
        assert batch.mask.dtype == th.bool
        lengths = mask.sum(axis=0)
        assert rows == lengths.max()
        # whole sequences, about batch_size steps: all but the first sequence fit in batch_size - 1 steps
        assert lengths[1:].sum() <= batch_size - 1
        assert lengths.sum() < batch_size + longest
        for name, array in arrays.items():
            assert getattr(batch, name).shape == (rows, width, *array.shape[2:]), name
        for column in range(width):
            length = int(lengths[column])
            assert mask[:length, column].all() and not mask[length:, column].any()  # padding after the end only
            slot, first = (int(v) for v in batch.observations[0, column, :2])
            seen_sequences.append((slot, first, length))
            seen_steps += [(t, slot) for t in range(first, first + length)]
            for name, array in arrays.items():
                np.testing.assert_array_equal(
                    getattr(batch, name)[:length, column].numpy(), array[first : first + length, slot], err_msg=name
                )
            stored = buffer.step_states[first]  # the states the sequence's first step started from
            for got, want in zip((*batch.states.pi, *batch.states.vf), (*stored.pi, *stored.vf)):
                assert got.shape == (1, width, want.shape[2])
                th.testing.assert_close(got[0, column], want[0, slot], rtol=0, atol=0)
    assert sorted(seen_sequences) == sorted(expected)
    assert sorted(seen_steps) == sorted((t, slot) for t in range(steps) for slot in range(slots))


@pytest.mark.parametrize("cell", CELLS)
def test_sequence_batches_hand_filled_buffer(cell: str) -> None:
    starts = np.zeros((6, 3), dtype=np.float32)
    starts[[0, 3], 0] = 1  # slot 0: episodes start at t = 0 and t = 3
    starts[[1, 5], 2] = 1  # slot 1 continues throughout; slot 2: starts at t = 1 and t = 5
    expected = {(0, 0, 3), (0, 3, 3), (1, 0, 6), (2, 0, 1), (2, 1, 4), (2, 5, 1)}
    assert expected_sequences(starts) == expected  # the helper agrees with the hand count
    buffer = fill_buffer(starts, cell)
    for batch_size in (1, 3, 4, 7, 18, 100):
        for seed in range(3):
            np.random.seed(seed)  # noqa: NPY002 - sequence_batches shuffles with numpy's global generator
            check_batches(buffer, batch_size, expected)
    # at most 4 steps: slot 1's 6 steps become [t0-3], [t4-5]; slot 2's [t1-4] becomes [t1-3], [t4]
    short = {(0, 0, 3), (0, 3, 1), (0, 4, 2), (1, 0, 4), (1, 4, 2), (2, 0, 1), (2, 1, 3), (2, 4, 1), (2, 5, 1)}
    assert expected_sequences(starts, 4) == short
    np.random.seed(0)  # noqa: NPY002
    check_batches(fill_buffer(starts, cell, max_length=4), 5, short)
    np.random.seed(0)  # noqa: NPY002
    assert [b.mask.shape[1] for b in buffer.sequence_batches(1)] == [1] * 6  # one sequence per batch
    assert [b.mask.shape[1] for b in buffer.sequence_batches(18)] == [6]  # everything in one batch


def test_sequence_batches_random_buffers() -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        steps, slots = int(rng.integers(1, 8)), int(rng.integers(1, 4))
        starts = (rng.random((steps, slots)) < 0.3).astype(np.float32)
        max_length = [None, 1, 2, 3][int(rng.integers(4))]
        buffer = fill_buffer(starts, "lstm", max_length)
        np.random.seed(int(rng.integers(1000)))  # noqa: NPY002
        check_batches(buffer, int(rng.integers(1, 10)), expected_sequences(starts, max_length))


# ---------------------------------------------------------------------------------------------------------------------
# 3. the policy


@pytest.mark.parametrize("cell", CELLS)
def test_forward_matches_reference_and_resets_only_starting_slots(cell: str) -> None:
    policy = make_policy(cell, low=-5.0, high=5.0, action_scale=1.7, sigma=0.3)
    reference = Reference(policy)
    obs = th.as_tensor(np.random.default_rng(0).normal(size=(3, OBS_DIM)), dtype=th.float32)
    states = random_states(policy, 3, seed=1)
    starts = th.tensor([1.0, 0.0, 1.0])
    with th.no_grad():
        actions, values, log_probs, new = policy(obs, states, starts, deterministic=True)
        sampled, _, sampled_log_probs, _ = policy(obs, states, starts)
    assert actions.shape == (3, 2) and values.shape == (3, 1) and log_probs.shape == (3,)
    for slot in range(3):
        reset = bool(starts[slot])
        pi = reference.zeros("pi") if reset else slot_state(states.pi, slot)
        vf = reference.zeros("vf") if reset else slot_state(states.vf, slot)
        mean, pi = reference.actor_step(_np(obs[slot]), pi)
        value, vf = reference.critic_step(_np(obs[slot]), vf)
        np.testing.assert_allclose(_np(actions[slot]), mean, atol=1e-5)
        np.testing.assert_allclose(float(values[slot, 0]), value, atol=1e-5)
        for got, want in zip((*slot_state(new.pi, slot), *slot_state(new.vf, slot)), (*pi, *vf)):
            np.testing.assert_allclose(got, want, atol=1e-5)
        np.testing.assert_allclose(float(log_probs[slot]), reference.log_prob(mean, mean), atol=1e-5)
        np.testing.assert_allclose(float(sampled_log_probs[slot]), reference.log_prob(mean, _np(sampled[slot])), atol=1e-4)
    # the kept slot really used its carried state: from zeros it would differ
    zero_mean, _ = reference.actor_step(_np(obs[1]), reference.zeros("pi"))
    zero_value, _ = reference.critic_step(_np(obs[1]), reference.zeros("vf"))
    assert np.abs(_np(actions[1]) - zero_mean).max() > 1e-3
    assert abs(float(values[1, 0]) - zero_value) > 1e-3


@pytest.mark.parametrize("cell", CELLS)
def test_evaluate_sequences_equals_step_by_step_forward(cell: str) -> None:
    policy = make_policy(cell, sigma=0.5)
    length, batch = 4, 3
    obs = th.as_tensor(np.random.default_rng(2).normal(size=(length, batch, OBS_DIM)), dtype=th.float32)
    initial = random_states(policy, batch, seed=3)
    states, no_start = initial, th.zeros(batch)
    step_actions, step_values, step_log_probs = [], [], []
    th.manual_seed(0)
    with th.no_grad():
        for t in range(length):
            values_by_critic = policy.predict_values(obs[t], states.vf, no_start)
            actions, values, log_probs, states = policy(obs[t], states, no_start)
            th.testing.assert_close(values_by_critic, values, rtol=0, atol=1e-6)
            step_actions.append(actions)
            step_values.append(values[:, 0])
            step_log_probs.append(log_probs)
        actions = th.stack(step_actions)
        values, log_probs, entropy = policy.evaluate_sequences(obs, actions, initial)
    assert values.shape == log_probs.shape == entropy.shape == (length, batch)
    th.testing.assert_close(values, th.stack(step_values), rtol=0, atol=1e-5)
    th.testing.assert_close(log_probs, th.stack(step_log_probs), rtol=0, atol=1e-5)
    # entropy of a 2-D Gaussian with std 0.5
    th.testing.assert_close(entropy, th.full((length, batch), 2 * (0.5 + LOG_SQRT_2PI + math.log(0.5))), rtol=0, atol=1e-5)
    # padding after the end does not change the outputs (causal cells)
    padded_obs = th.cat([obs, 50 * th.ones(2, batch, OBS_DIM)])
    padded_actions = th.cat([actions, th.ones(2, batch, 2)])
    with th.no_grad():
        padded_values, padded_log_probs, _ = policy.evaluate_sequences(padded_obs, padded_actions, initial)
    th.testing.assert_close(padded_values[:length], values, rtol=0, atol=1e-6)
    th.testing.assert_close(padded_log_probs[:length], log_probs, rtol=0, atol=1e-6)


@pytest.mark.parametrize("cell", CELLS)
def test_predict_values_resets_where_episode_starts(cell: str) -> None:
    policy = make_policy(cell)
    reference = Reference(policy)
    obs = th.as_tensor(np.random.default_rng(4).normal(size=(2, OBS_DIM)), dtype=th.float32)
    states = random_states(policy, 2, seed=5)
    with th.no_grad():
        values = policy.predict_values(obs, states.vf, th.tensor([0.0, 1.0]))
    np.testing.assert_allclose(float(values[0, 0]), reference.critic_step(_np(obs[0]), slot_state(states.vf, 0))[0], atol=1e-5)
    np.testing.assert_allclose(float(values[1, 0]), reference.critic_step(_np(obs[1]), reference.zeros("vf"))[0], atol=1e-5)


@pytest.mark.parametrize("cell", CELLS)
def test_predict_carries_the_actor_state_and_resets_at_episode_start(cell: str) -> None:
    # action_scale 3 and actions in [-2, 2]: some means are clipped
    policy = make_policy(cell, low=-2.0, high=2.0, action_scale=3.0, seed=11, scale=1.0)
    reference = Reference(policy)
    rng = np.random.default_rng(5)
    n = 4
    flags = np.array([[1, 1, 1, 1], [0, 0, 0, 0], [0, 1, 0, 1], [1, 0, 0, 0], [0, 0, 1, 0]], dtype=bool)
    ref_states = [reference.zeros("pi") for _ in range(n)]
    state, clipped, inside = None, 0, 0
    for t, starts in enumerate(flags):
        obs = rng.normal(size=(n, OBS_DIM)).astype(np.float32)
        actions, state = policy.predict(obs, state, episode_start=None if t == 0 else starts, deterministic=True)
        assert actions.shape == (n, 2) and isinstance(actions, np.ndarray)
        assert len(state) == (1 if cell == "gru" else 2) and all(s.shape == (1, n, PI_HIDDEN) for s in state)
        for slot in range(n):
            if starts[slot]:
                ref_states[slot] = reference.zeros("pi")
            mean, ref_states[slot] = reference.actor_step(obs[slot], ref_states[slot])
            np.testing.assert_allclose(actions[slot], np.clip(mean, -2.0, 2.0), atol=1e-5)
            clipped += int((np.abs(mean) > 2.0).sum())
            inside += int((np.abs(mean) < 2.0).sum())
            for got, want in zip(state, ref_states[slot]):
                np.testing.assert_allclose(got[0, slot], want, atol=1e-5)
    assert clipped > 0 and inside > 0
    # without the reset flags the carried state is used: slot 1 at t = 2 gives another action
    obs = rng.normal(size=(n, OBS_DIM)).astype(np.float32)
    kept, _ = policy.predict(obs, state, episode_start=np.zeros(n, dtype=bool), deterministic=True)
    reset, _ = policy.predict(obs, state, episode_start=np.ones(n, dtype=bool), deterministic=True)
    fresh, _ = policy.predict(obs, None, deterministic=True)
    np.testing.assert_array_equal(reset, fresh)
    assert np.abs(kept - fresh).max() > 1e-3


@pytest.mark.parametrize("cell", CELLS)
def test_predict_single_observation(cell: str) -> None:
    policy = make_policy(cell, seed=3)
    reference = Reference(policy)
    obs = np.array([0.3, -1.2, 0.8], dtype=np.float32)
    action, state = policy.predict(obs, deterministic=True)
    assert action.shape == (2,)
    assert all(s.shape == (1, 1, PI_HIDDEN) for s in state)
    mean, ref_state = reference.actor_step(obs, reference.zeros("pi"))
    np.testing.assert_allclose(action, np.clip(mean, -1, 1), atol=1e-5)
    # second step from the returned state, then a reset
    action2, state2 = policy.predict(obs, state, episode_start=np.array([False]), deterministic=True)
    mean2, _ = reference.actor_step(obs, ref_state)
    np.testing.assert_allclose(action2, np.clip(mean2, -1, 1), atol=1e-5)
    action3, _ = policy.predict(obs, state2, episode_start=np.array([True]), deterministic=True)
    np.testing.assert_allclose(action3, action, atol=1e-6)
    batched, _ = policy.predict(obs[None], deterministic=True)
    np.testing.assert_array_equal(batched[0], action)


@pytest.mark.parametrize("cell", CELLS)
def test_sigma_is_fixed_and_not_trained(cell: str) -> None:
    model = make_model(cell, policy_kwargs={"sigma": 0.35}, learning_rate=1e-2)
    policy = model.policy
    assert not policy.log_std.requires_grad
    np.testing.assert_allclose(_np(policy.log_std), [math.log(0.35)] * 2, rtol=1e-6)
    optimised = [p for group in policy.optimizer.param_groups for p in group["params"]]
    assert all(p is not policy.log_std for p in optimised)
    assert len(optimised) == sum(1 for p in policy.parameters() if p is not policy.log_std)
    before = {name: p.detach().clone() for name, p in policy.named_parameters()}
    model.learn(total_timesteps=14)
    after = dict(policy.named_parameters())
    th.testing.assert_close(after["log_std"], before["log_std"], rtol=0, atol=0)
    assert not after["log_std"].requires_grad
    assert any(not th.equal(after[name], before[name]) for name in before if name != "log_std")  # training happened


# ---------------------------------------------------------------------------------------------------------------------
# 4. collect_rollouts


class Recorder(BaseCallback):
    """Keeps the policy (as a :class:`Reference`) at each rollout's start and copies of the buffer at its end."""

    def __init__(self) -> None:
        super().__init__()
        self.rollouts: list[dict[str, Any]] = []

    def _on_rollout_start(self) -> None:
        self.rollouts.append({"reference": Reference(self.model.policy)})

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        record = self.rollouts[-1]
        for name in ("observations", "actions", "rewards", "episode_starts", "values", "log_probs", "returns", "advantages"):
            record[name] = getattr(buffer, name).copy()
        record["step_states"] = [cloned(step) for step in buffer.step_states]
        record["initial_states"] = record["step_states"][0]
        record["last_states"] = cloned(self.model._last_states)

    def _on_step(self) -> bool:
        return True


@pytest.mark.parametrize("cell", CELLS)
def test_collect_rollouts_replayed_step_by_step(cell: str) -> None:
    gamma, lam, steps, slots = 0.9, 0.8, 7, 2
    model = make_model(cell, gamma=gamma, gae_lambda=lam, learning_rate=3e-3)
    randomize(model.policy, seed=21, scale=0.5)
    recorder = Recorder()
    model.learn(total_timesteps=2 * steps * slots, callback=recorder)
    assert len(recorder.rollouts) == 2
    first, second = recorder.rollouts
    # the second rollout starts from the states carried out of the first one, which are not zeros
    for got, want in zip(
        (*second["initial_states"].pi, *second["initial_states"].vf), (*first["last_states"].pi, *first["last_states"].vf)
    ):
        th.testing.assert_close(got, want, rtol=0, atol=0)
        assert want.abs().max() > 1e-2
    for tensor in (*first["initial_states"].pi, *first["initial_states"].vf):
        assert not tensor.any()
    # replay both rollouts with each rollout's weights, resetting a slot's states only at its episode starts
    ref_pi = [first["reference"].zeros("pi") for _ in range(slots)]
    ref_vf = [first["reference"].zeros("vf") for _ in range(slots)]
    timeout_checks = 0
    for index, rollout in enumerate(recorder.rollouts):
        reference = rollout["reference"]
        for slot in range(slots):
            for got, want in zip(slot_state(rollout["initial_states"].pi, slot), ref_pi[slot]):
                np.testing.assert_allclose(got, want, atol=1e-5)
            for got, want in zip(slot_state(rollout["initial_states"].vf, slot), ref_vf[slot]):
                np.testing.assert_allclose(got, want, atol=1e-5)
        values = np.zeros((steps, slots))
        rewards = np.zeros((steps, slots))
        dones = np.zeros(slots, dtype=bool)
        for t in range(steps):
            g = index * steps + t  # global step since learn() reset the envs
            for slot in range(slots):
                length = LENGTHS[slot]
                step, episode = g % length, g // length
                obs = rollout["observations"][t, slot]
                np.testing.assert_array_equal(obs, [slot, step, episode])  # what the network saw
                assert rollout["episode_starts"][t, slot] == (step == 0)
                if step == 0:
                    ref_pi[slot], ref_vf[slot] = reference.zeros("pi"), reference.zeros("vf")
                entering = rollout["step_states"][t]  # stored for the update: the states this step started from
                for got, want in zip(
                    (*slot_state(entering.pi, slot), *slot_state(entering.vf, slot)), (*ref_pi[slot], *ref_vf[slot])
                ):
                    np.testing.assert_allclose(got, want, atol=1e-5)
                mean, ref_pi[slot] = reference.actor_step(obs, ref_pi[slot])
                values[t, slot], ref_vf[slot] = reference.critic_step(obs, ref_vf[slot])
                np.testing.assert_allclose(rollout["values"][t, slot], values[t, slot], atol=2e-5)
                log_prob = reference.log_prob(mean, rollout["actions"][t, slot])
                np.testing.assert_allclose(rollout["log_probs"][t, slot], log_prob, atol=1e-4)
                rewards[t, slot] = step_reward(slot, step + 1)
                dones[slot] = step + 1 == length
                if dones[slot] and TRUNCATES[slot]:  # time-out: + gamma V(terminal obs | critic state after this step)
                    terminal_value, _ = reference.critic_step(np.array([slot, length, episode]), ref_vf[slot])
                    from_zeros, _ = reference.critic_step(np.array([slot, length, episode]), reference.zeros("vf"))
                    assert abs(terminal_value - from_zeros) > 1e-3  # the carried state matters
                    rewards[t, slot] += gamma * terminal_value
                    timeout_checks += 1
                np.testing.assert_allclose(rollout["rewards"][t, slot], rewards[t, slot], rtol=1e-5, atol=2e-5)
        # GAE with the critic's value of the next observation from the carried state (zeros after an episode's end)
        next_values = np.zeros(slots)
        for slot in range(slots):
            g = (index + 1) * steps
            state = reference.zeros("vf") if dones[slot] else ref_vf[slot]
            next_obs = np.array([slot, g % LENGTHS[slot], g // LENGTHS[slot]])
            next_values[slot] = reference.critic_step(next_obs, state)[0]
        advantages, gae = np.zeros((steps, slots)), np.zeros(slots)
        for t in reversed(range(steps)):
            if t == steps - 1:
                keep, following = 1.0 - dones, next_values
            else:
                keep, following = 1.0 - rollout["episode_starts"][t + 1], values[t + 1]
            gae = rewards[t] + gamma * following * keep - values[t] + gamma * lam * keep * gae
            advantages[t] = gae
        np.testing.assert_allclose(rollout["advantages"], advantages, atol=1e-4)
        np.testing.assert_allclose(rollout["returns"], advantages + values, atol=1e-4)
        for slot in range(slots):  # the states carried out of the rollout
            for got, want in zip(slot_state(rollout["last_states"].pi, slot), ref_pi[slot]):
                np.testing.assert_allclose(got, want, atol=1e-5)
            for got, want in zip(slot_state(rollout["last_states"].vf, slot), ref_vf[slot]):
                np.testing.assert_allclose(got, want, atol=1e-5)
    # slot 1 times out at global steps 4 and 9 (the second across the rollouts' boundary)
    assert timeout_checks == 2
    for got, want in zip(
        (*model._last_states.pi, *model._last_states.vf), (*second["last_states"].pi, *second["last_states"].vf)
    ):
        th.testing.assert_close(got, want, rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------------------------------
# 5. save and load


@pytest.mark.parametrize("cell", CELLS)
def test_save_load_round_trip(cell: str, tmp_path: Path) -> None:
    policy_kwargs = {"net_arch": NET_ARCH, "cell": cell, "sigma": 0.4, "action_scale": 1.5}
    model = RecurrentFormationPPO(
        env=make_env(), n_steps=7, batch_size=7, n_epochs=1, seed=0, device="cpu", policy_kwargs=policy_kwargs
    )
    model.learn(total_timesteps=14)
    path = tmp_path / "model.zip"
    model.save(path)
    data, params, _ = load_from_zip_file(path, device="cpu")
    assert "_last_states" not in data
    assert "policy" in params
    loaded = RecurrentFormationPPO.load(path, device="cpu")
    assert isinstance(loaded.policy, RecurrentFormationPolicy)
    assert loaded.policy_kwargs == policy_kwargs
    assert loaded.policy.cell == cell
    assert loaded.policy.net_arch == {"pi": [8], "pi_recurrent": 6, "pi_after": [], **NET_ARCH}
    assert loaded.policy.sigma == 0.4 and loaded.policy.action_scale == 1.5
    np.testing.assert_allclose(_np(loaded.policy.log_std), [math.log(0.4)] * 2, rtol=1e-6)
    for tensor in (*loaded._last_states.pi, *loaded._last_states.vf):  # fresh zero states for the saved n_envs
        assert tensor.shape[1] == 2 and not tensor.any()
    for name, tensor in model.policy.state_dict().items():
        th.testing.assert_close(loaded.policy.state_dict()[name], tensor, rtol=0, atol=0)
    rng = np.random.default_rng(9)
    state_a = state_b = None
    for t in range(3):
        obs = rng.normal(size=(3, OBS_DIM)).astype(np.float32)
        starts = np.array([t == 0, t == 2, False])
        actions_a, state_a = model.predict(obs, state_a, episode_start=starts, deterministic=True)
        actions_b, state_b = loaded.predict(obs, state_b, episode_start=starts, deterministic=True)
        np.testing.assert_array_equal(actions_a, actions_b)
        for a, b in zip(state_a, state_b):
            np.testing.assert_array_equal(a, b)
        th.manual_seed(t)
        sampled_a, _ = model.predict(obs, state_a, deterministic=False)
        th.manual_seed(t)
        sampled_b, _ = loaded.predict(obs, state_b, deterministic=False)
        np.testing.assert_array_equal(sampled_a, sampled_b)
    # the loaded model trains further
    loaded.set_env(make_env())
    loaded.learn(total_timesteps=14)


def test_policy_save_load_round_trip(tmp_path: Path) -> None:
    policy = make_policy("gru", sigma=0.4, action_scale=1.5)
    policy.save(tmp_path / "policy.pt")
    loaded = RecurrentFormationPolicy.load(tmp_path / "policy.pt", device="cpu")
    obs = np.ones((2, OBS_DIM), dtype=np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0])


# ---------------------------------------------------------------------------------------------------------------------
# 6. validation


BOX_OBS = spaces.Box(-1.0, 1.0, (OBS_DIM,), np.float32)
BOX_ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)


@pytest.mark.parametrize(
    ("observation_space", "action_space", "kwargs", "match"),
    [
        (BOX_OBS, BOX_ACT, {"cell": "rnn"}, "cell must be one of"),
        (BOX_OBS, BOX_ACT, {"net_arch": {"pi": [8], "qf": [4]}}, r"unknown net_arch keys \['qf'\]"),
        (spaces.Discrete(4), BOX_ACT, {}, "flat Box observation space"),
        (spaces.Box(-1.0, 1.0, (2, 3), np.float32), BOX_ACT, {}, "flat Box observation space"),
        (BOX_OBS, spaces.Discrete(3), {}, "Box action space"),
        (BOX_OBS, BOX_ACT, {"use_sde": True}, "use_sde"),
        (BOX_OBS, BOX_ACT, {"sigma": 0.0}, "sigma"),
        (BOX_OBS, BOX_ACT, {"sigma": math.nan}, "sigma"),
        (BOX_OBS, BOX_ACT, {"action_scale": -1.0}, "action_scale"),
    ],
)
def test_policy_validation(observation_space: spaces.Space, action_space: spaces.Space, kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RecurrentFormationPolicy(observation_space, action_space, lambda _: 1e-3, **kwargs)


class DiscreteActionEnv(CountingEnv):
    def __init__(self) -> None:
        super().__init__(0, 3, False)
        self.action_space = spaces.Discrete(3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"policy_kwargs": {"cell": "rnn"}}, "cell must be one of"),
        ({"policy_kwargs": {"net_arch": {"pi_recurent": 4}}}, "unknown net_arch keys"),
        ({"use_sde": True}, "use_sde"),
        ({"policy": ActorCriticPolicy}, "trains a RecurrentFormationPolicy"),
        ({"policy": "MlpPolicy"}, "trains a RecurrentFormationPolicy"),
        ({"rollout_buffer_class": RolloutBuffer}, "RecurrentRolloutBuffer"),
        ({"env": DummyVecEnv([DiscreteActionEnv])}, "Box action space"),
    ],
)
def test_ppo_validation(kwargs: dict, match: str) -> None:
    settings = {
        "policy": RecurrentFormationPolicy,
        "env": make_env(),
        "n_steps": 7,
        "batch_size": 7,
        "device": "cpu",
        **kwargs,
    }
    with pytest.raises(ValueError, match=match):
        RecurrentFormationPPO(**settings)


def test_ppo_accepts_the_policy_name_and_a_subclass() -> None:
    class Subclass(RecurrentFormationPolicy):
        pass

    small = {"n_steps": 7, "batch_size": 7, "device": "cpu", "policy_kwargs": {"net_arch": NET_ARCH}}
    by_name = RecurrentFormationPPO("RecurrentFormationPolicy", make_env(), **small)
    assert type(by_name.policy) is RecurrentFormationPolicy
    assert isinstance(by_name.rollout_buffer, RecurrentRolloutBuffer)
    by_subclass = RecurrentFormationPPO(Subclass, make_env(), **small)
    assert type(by_subclass.policy) is Subclass


def test_max_sequence_length_is_validated_and_saved(tmp_path: Path) -> None:
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="max_sequence_length"):
            make_model("gru", max_sequence_length=bad)
    model = make_model("gru", max_sequence_length=3)
    assert model.rollout_buffer.max_sequence_length == 3
    model.save(tmp_path / "model.zip")
    loaded = RecurrentFormationPPO.load(tmp_path / "model.zip", device="cpu")
    assert loaded.max_sequence_length == loaded.rollout_buffer.max_sequence_length == 3
    assert make_model("gru").max_sequence_length == DEFAULT_MAX_SEQUENCE_LENGTH == 16
