"""Tests of :class:`FormationPolicy`: thesis network sizes, orthogonal init, bounded mean, fixed sigma, team critic."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn

from sb3_formation.sb3.networks import gaussian_actions
from sb3_formation.sb3.policies import FormationPolicy, TeamCriticExtractor

D = 5  # length of one agent's observation in the dummy envs
N = 3  # team size for the team critic


class DummyEnv(gym.Env):
    """Random Box observations of length ``obs_dim``, 2-D actions in [-1, 1], reward -|a|, 12-step episodes."""

    def __init__(self, obs_dim: int = D) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, (obs_dim,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self._t = 0

    def _obs(self) -> np.ndarray:
        return self.np_random.uniform(-1.0, 1.0, self.observation_space.shape).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._t = 0
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self._t += 1
        return self._obs(), -float(np.linalg.norm(action)), False, self._t >= 12, {}


def make_vec_env(obs_dim: int = D, n_envs: int = 2) -> DummyVecEnv:
    return DummyVecEnv([lambda: DummyEnv(obs_dim) for _ in range(n_envs)])


def make_model(obs_dim: int = D, seed: int = 0, **policy_kwargs) -> PPO:
    """A PPO with tiny rollouts (2 envs x 16 steps) and shuffled minibatches of 8."""
    return PPO(
        FormationPolicy,
        make_vec_env(obs_dim),
        n_steps=16,
        batch_size=8,
        n_epochs=2,
        seed=seed,
        device="cpu",
        policy_kwargs=policy_kwargs,
    )


def observations(obs_dim: int, n: int = 16, seed: int = 0) -> th.Tensor:
    return th.as_tensor(np.random.default_rng(seed).uniform(-1.0, 1.0, (n, obs_dim)), dtype=th.float32)


def action_mean(policy: FormationPolicy, obs: th.Tensor) -> th.Tensor:
    with th.no_grad():
        return policy.get_distribution(obs).distribution.mean


def value(policy: FormationPolicy, obs: th.Tensor) -> th.Tensor:
    with th.no_grad():
        return policy.predict_values(obs)


def linears(module: nn.Module) -> list[nn.Linear]:
    return [layer for layer in module.modules() if isinstance(layer, nn.Linear)]


def layer_shapes(module: nn.Module) -> list[tuple[int, int]]:
    return [(layer.in_features, layer.out_features) for layer in linears(module)]


def activations(sequential: nn.Sequential) -> list[type[nn.Module]]:
    return [type(layer) for layer in sequential if not isinstance(layer, nn.Linear)]


def assert_orthogonal(weight: th.Tensor, gain: float) -> None:
    """W W^T = gain^2 I (more inputs than outputs) or W^T W = gain^2 I (more outputs) up to 1e-4."""
    w = weight.detach().double()
    gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
    expected = gain**2 * th.eye(gram.shape[0], dtype=th.float64)
    assert th.allclose(gram, expected, atol=1e-4, rtol=0), f"{tuple(w.shape)} is not orthogonal with gain {gain}"


# Network structure ---------------------------------------------------------------------------------------------


def test_default_layers_and_activations() -> None:
    """Thesis figs 4.1-4.2: actor 512 -> 256 -> 2, critic 512 -> 512 -> 512 -> 1, tanh hidden layers."""
    policy = make_model().policy
    assert isinstance(policy, FormationPolicy)
    extractor = policy.mlp_extractor
    assert layer_shapes(extractor.policy_net) + layer_shapes(policy.action_net) == [(D, 512), (512, 256), (256, 2)]
    assert layer_shapes(extractor.value_net) + layer_shapes(policy.value_net) == [(D, 512), (512, 512), (512, 512), (512, 1)]
    assert activations(extractor.policy_net) == [nn.Tanh] * 2
    assert activations(extractor.value_net) == [nn.Tanh] * 3
    assert isinstance(policy.value_net, nn.Linear)  # linear value output


def test_team_critic_layers_and_activations() -> None:
    """Thesis fig. 4.3: two 512 layers per agent (shared), mean, 512 -> 512 -> 1; the actor reads D values."""
    policy = make_model(D * (1 + N), team_size=N).policy
    extractor = policy.mlp_extractor
    assert isinstance(extractor, TeamCriticExtractor)
    assert (extractor.obs_dim, extractor.team_size) == (D, N)
    assert layer_shapes(extractor.policy_net) + layer_shapes(policy.action_net) == [(D, 512), (512, 256), (256, 2)]
    assert layer_shapes(extractor.agent_net) == [(D, 512), (512, 512)]
    assert layer_shapes(extractor.team_net) + layer_shapes(policy.value_net) == [(512, 512), (512, 512), (512, 1)]
    assert activations(extractor.policy_net) == [nn.Tanh] * 2
    assert activations(extractor.agent_net) == [nn.Tanh] * 2
    assert activations(extractor.team_net) == [nn.Tanh] * 2


@pytest.mark.parametrize("team_size", [None, N])
def test_orthogonal_init_with_sb3_gains(team_size: int | None) -> None:
    """Every layer orthogonal with zero bias: gain sqrt(2) hidden, 0.01 action output, 1 value output."""
    obs_dim = D if team_size is None else D * (1 + team_size)
    policy = make_model(obs_dim, team_size=team_size).policy
    hidden = linears(policy.mlp_extractor)
    assert len(hidden) == (5 if team_size is None else 6)
    for layer, gain in [*((layer, math.sqrt(2)) for layer in hidden), (policy.action_net, 0.01), (policy.value_net, 1.0)]:
        assert_orthogonal(layer.weight, gain)
        assert th.count_nonzero(layer.bias) == 0


# Actor mean and sigma ------------------------------------------------------------------------------------------


def test_action_mean_bounded_and_scaled() -> None:
    """mean = action_scale * tanh(.): within [-scale, scale] even when saturated, and exactly 0.01 x with scale 0.01."""
    full = make_model(seed=3).policy
    small = make_model(seed=4, action_scale=0.01).policy
    with th.no_grad():
        full.action_net.weight.mul_(1000.0)  # drive the tanh into saturation
    small.load_state_dict(full.state_dict())
    obs = observations(D, n=64)
    mean_full, mean_small = action_mean(full, obs), action_mean(small, obs)
    assert mean_full.shape == (64, 2)
    assert mean_full.abs().max() <= 1.0 and mean_full.abs().max() > 0.99
    assert mean_small.abs().max() <= 0.01
    assert th.equal(mean_small, 0.01 * mean_full)


def test_sigma_fixed_through_training() -> None:
    """log_std = log(sigma) is not trained: no grad, not in the optimizer, unchanged after PPO.learn."""
    model = make_model()
    policy = model.policy
    assert policy.log_std.requires_grad is False
    assert all(param is not policy.log_std for group in policy.optimizer.param_groups for param in group["params"])
    log_std_before = policy.log_std.detach().clone()
    weights_before = policy.action_net.weight.detach().clone()
    model.learn(total_timesteps=64)
    assert th.equal(policy.log_std, log_std_before)
    assert th.allclose(policy.log_std.exp(), th.full((2,), 0.7), rtol=0, atol=1e-7)
    assert policy.log_std.requires_grad is False
    assert not th.equal(policy.action_net.weight, weights_before)  # the rest of the network did train
    with th.no_grad():
        stddev = policy.get_distribution(observations(D)).distribution.stddev
    assert th.allclose(stddev, th.full_like(stddev, 0.7), rtol=0, atol=1e-7)


def test_custom_sigma() -> None:
    policy = make_model(sigma=0.3).policy
    assert th.allclose(policy.log_std.exp(), th.full((2,), 0.3), rtol=0, atol=1e-7)


# Team critic ---------------------------------------------------------------------------------------------------


def block(i: int) -> slice:
    """Slice of team agent i's observation in a team-critic slot ([own, agent 0, ..., agent n-1])."""
    return slice(D * (1 + i), D * (2 + i))


def test_team_critic_sees_team_actor_sees_own() -> None:
    """A teammate's block moves the value, not the action; the own block moves the action, not the value."""
    policy = make_model(D * (1 + N), team_size=N).policy
    obs = observations(D * (1 + N))
    mean, val = action_mean(policy, obs), value(policy, obs)

    teammate = obs.clone()
    teammate[:, block(2)] = observations(D, seed=1)
    assert th.equal(action_mean(policy, teammate), mean)
    assert not th.allclose(value(policy, teammate), val)

    own = obs.clone()
    own[:, :D] = observations(D, seed=2)
    assert not th.allclose(action_mean(policy, own), mean)
    assert th.equal(value(policy, own), val)


def test_team_critic_invariant_to_agent_order() -> None:
    """Mean pooling: permuting the n team blocks leaves the value unchanged."""
    policy = make_model(D * (1 + N), team_size=N).policy
    obs = observations(D * (1 + N))
    permuted = obs.clone()
    for target, source in enumerate([2, 0, 1]):
        permuted[:, block(target)] = obs[:, block(source)]
    assert not th.equal(permuted, obs)
    assert th.allclose(value(policy, permuted), value(policy, obs), rtol=0, atol=1e-6)


def test_team_critic_trains_with_shuffled_minibatches() -> None:
    model = make_model(D * (1 + N), team_size=N)
    weights_before = model.policy.mlp_extractor.agent_net[0].weight.detach().clone()
    model.learn(total_timesteps=64)
    assert not th.equal(model.policy.mlp_extractor.agent_net[0].weight, weights_before)
    assert th.allclose(model.policy.log_std.exp(), th.full((2,), 0.7), rtol=0, atol=1e-7)


# Save and load -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("team_size", [None, N])
def test_save_load_round_trip(tmp_path: Path, team_size: int | None) -> None:
    """PPO.save / PPO.load and policy.save / FormationPolicy.load restore the same actions and values."""
    obs_dim = D if team_size is None else D * (1 + team_size)
    model = make_model(obs_dim, sigma=0.5, action_scale=0.01, team_size=team_size)
    model.learn(total_timesteps=32)
    model.save(tmp_path / "model.zip")
    model.policy.save(tmp_path / "policy.zip")
    obs = observations(obs_dim).numpy()
    actions, _ = model.predict(obs, deterministic=True)

    loaded = PPO.load(tmp_path / "model.zip", device="cpu")
    alone = FormationPolicy.load(tmp_path / "policy.zip", device="cpu")
    for policy in (loaded.policy, alone):
        assert isinstance(policy, FormationPolicy)
        assert (policy.sigma, policy.action_scale, policy.team_size) == (0.5, 0.01, team_size)
        assert policy.log_std.requires_grad is False
        assert th.equal(action_mean(policy, th.as_tensor(obs)), action_mean(model.policy, th.as_tensor(obs)))
        assert th.equal(value(policy, th.as_tensor(obs)), value(model.policy, th.as_tensor(obs)))
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    loaded.set_env(make_vec_env(obs_dim))
    loaded.learn(total_timesteps=32)  # the restored optimizer state matches its parameter groups
    assert th.allclose(loaded.policy.log_std.exp(), th.full((2,), 0.5), rtol=0, atol=1e-7)


# Validation ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("obs_dim", "policy_kwargs", "match"),
    [
        (D * (1 + N) + 1, dict(team_size=N), "not divisible by 1 \\+ team_size"),
        (D * (1 + N), dict(team_size=N, net_arch=dict(pi=[8], vf=[8])), "at least 2 widths"),
        (D * (1 + N), dict(team_size=0), "team_size"),
        (D, dict(sigma=0.0), "sigma"),
        (D, dict(action_scale=-1.0), "action_scale"),
        (D, dict(log_std_init=0.0), "instead of log_std_init"),
    ],
)
def test_invalid_arguments(obs_dim: int, policy_kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_model(obs_dim, **policy_kwargs)


def test_rejects_sde_and_discrete_actions() -> None:
    with pytest.raises(ValueError, match="use_sde"):
        PPO(FormationPolicy, make_vec_env(), use_sde=True, device="cpu")
    box = spaces.Box(-1.0, 1.0, (D,), dtype=np.float32)
    with pytest.raises(ValueError, match="Box action space"):
        FormationPolicy(box, spaces.Discrete(3), lambda _: 1e-3)


def test_gaussian_actions_is_sb3s_gaussian_without_argument_checks() -> None:
    mean, log_std = th.tensor([[0.25, -0.5], [0.0, 1.0]]), th.tensor([-0.5, 0.3])
    ours = gaussian_actions(DiagGaussianDistribution(2), mean, log_std)
    sb3 = DiagGaussianDistribution(2).proba_distribution(mean, log_std)
    assert th.equal(ours.distribution.scale, sb3.distribution.scale) and th.equal(ours.distribution.mean, mean)
    th.manual_seed(3)
    sampled = ours.sample()
    th.manual_seed(3)
    assert th.equal(sampled, sb3.sample())  # the same draws
    assert th.equal(ours.log_prob(sampled), sb3.log_prob(sampled)) and th.equal(ours.entropy(), sb3.entropy())
    nan_mean = th.tensor([[float("nan"), 0.0]])
    unchecked = gaussian_actions(DiagGaussianDistribution(2), nan_mean, log_std)  # torch's checks would raise here
    assert unchecked.distribution._validate_args is False and th.isnan(unchecked.mode()).any()  # left to the VecEnv


@pytest.mark.parametrize("team_size", [None, 2])
@pytest.mark.parametrize("rows", [1, 7, 96])
def test_deterministic_actions_are_predicts_to_the_bit(team_size: int | None, rows: int) -> None:
    """The evaluation's fast path gives what SB3's ``predict(..., deterministic=True)`` gives, bit for bit, with the
    action space's clip (saturated means included)."""
    obs_dim = D * 3 if team_size else D
    policy = make_model(obs_dim=obs_dim, seed=5, team_size=team_size, action_scale=1.0).policy
    with th.no_grad():
        policy.action_net.weight.mul_(50.0)  # some means at the bounds
    obs = observations(obs_dim, n=rows, seed=rows).numpy()
    expected, _ = policy.predict(obs, deterministic=True)
    actions = policy.deterministic_actions(obs)
    assert actions.dtype == expected.dtype and np.array_equal(actions, expected)
