"""Recurrent actor-critic PPO for the chapter-5 set-up (thesis 5.1.2, figs 5.1 and 5.2), without sb3-contrib.

- :class:`RecurrentFormationPolicy`: actor 512 dense -> 256 recurrent -> 2 (fig. 5.1), critic 512 dense -> 512
  recurrent -> 256 dense -> 1 (fig. 5.2); GRU or LSTM cells; tanh activations, bounded action mean and fixed sigma
  as in :class:`~sb3_formation.policies.FormationPolicy`.
- :class:`RecurrentRolloutBuffer`: SB3's ``RolloutBuffer`` plus the hidden states each step started from. For training
  it cuts every slot's rollout into sequences at episode starts (and every ``max_sequence_length`` steps), so a
  sequence never spans two slots or two episodes, and builds minibatches of whole sequences, padded to one length and
  masked, without a Python loop over the sequences.
- :class:`RecurrentFormationPPO`: SB3's ``PPO`` whose rollouts carry the hidden states (reset per slot at its
  episode's start) and whose update replays each sequence from its stored starting state.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from sb3_formation.sb3.policies import DEFAULT_SIGMA

#: Recurrent cell types.
CELLS = ("gru", "lstm")
#: Thesis figs 5.1 and 5.2: actor 512 -> (256 recurrent) -> 2; critic 512 -> (512 recurrent) -> 256 -> 1.
DEFAULT_RECURRENT_NET_ARCH: dict[str, Any] = {
    "pi": [512],
    "pi_recurrent": 256,
    "pi_after": [],
    "vf": [512],
    "vf_recurrent": 512,
    "vf_after": [256],
}

#: Longest sequence replayed in an update: 16 steps. benchmarks/sequence_length.py: a 512-step minibatch of the thesis's
#: networks as 32 sequences of 16 steps takes 0.45x (GRU) / 0.68x (LSTM) the gradient time of 4 sequences of 128;
#: shorter sequences gain little more. RLlib, the thesis's tool, cuts at 20 by default.
DEFAULT_MAX_SEQUENCE_LENGTH = 16

#: A recurrent head's state: ``(h,)`` for a GRU, ``(h, c)`` for an LSTM; each ``(1, n, hidden)``.
CellState = tuple[th.Tensor, ...]


class RecurrentStates(NamedTuple):
    """Hidden states of the actor (``pi``) and of the critic (``vf``) for a batch of slots."""

    pi: CellState
    vf: CellState

    def select(self, rows: th.Tensor | np.ndarray | slice) -> RecurrentStates:
        """The states of some slots (rows of the batch dimension)."""
        return RecurrentStates(*(tuple(tensor[:, rows] for tensor in state) for state in self))

    def masked(self, keep: th.Tensor) -> RecurrentStates:
        """Every state multiplied by ``keep`` (``(n,)``, 0 to reset a slot, 1 to keep it)."""
        return RecurrentStates(_kept(self.pi, keep), _kept(self.vf, keep))


def _kept(state: CellState, keep: th.Tensor) -> CellState:
    """``state`` with slot i's rows multiplied by ``keep[i]`` (0 resets the slot, 1 keeps it)."""
    factor = keep.float().view(1, -1, 1)
    return tuple(tensor * factor for tensor in state)


def _mlp(input_dim: int, widths: list[int], activation_fn: type[nn.Module]) -> tuple[nn.Sequential, int]:
    layers: list[nn.Module] = []
    for width in widths:
        layers += [nn.Linear(input_dim, width), activation_fn()]
        input_dim = width
    return nn.Sequential(*layers), input_dim


class RecurrentHead(nn.Module):
    """Dense layers, one recurrent layer, dense layers: the body of the recurrent actor or critic.

    :param input_dim: observation size
    :param before: widths of the dense layers before the recurrent one
    :param hidden: width of the recurrent layer
    :param after: widths of the dense layers after it
    :param cell: ``"gru"`` or ``"lstm"``
    :param activation_fn: activation of the dense layers
    """

    def __init__(
        self, input_dim: int, before: list[int], hidden: int, after: list[int], cell: str, activation_fn: type[nn.Module]
    ) -> None:
        super().__init__()
        self.before, width = _mlp(input_dim, before, activation_fn)
        self.rnn = (nn.GRU if cell == "gru" else nn.LSTM)(width, hidden)
        self.after, self.output_dim = _mlp(hidden, after, activation_fn)
        self.cell, self.hidden = cell, hidden

    def initial_state(self, n: int, device: th.device) -> CellState:
        """Zero states for ``n`` slots."""
        count = 1 if self.cell == "gru" else 2
        return tuple(th.zeros(1, n, self.hidden, device=device) for _ in range(count))

    def forward(self, inputs: th.Tensor, state: CellState) -> tuple[th.Tensor, CellState]:
        """Run over ``(L, B, input_dim)`` sequences from ``state``; return ``(L, B, output_dim)`` and the final state."""
        outputs, final = self.rnn(self.before(inputs), state[0] if self.cell == "gru" else state)
        return self.after(outputs), (final,) if self.cell == "gru" else tuple(final)


class RecurrentFormationPolicy(BasePolicy):
    """Recurrent actor-critic of thesis chapter 5 (figs 5.1 and 5.2) for :class:`RecurrentFormationPPO`.

    The actor and the critic each have their own recurrent state. The action distribution is a diagonal Gaussian with
    mean ``action_scale * tanh(action_net(actor output))`` and a fixed standard deviation ``sigma`` (not trained).
    :meth:`predict` has SB3's signature with the actor's state: ``predict(observation, state, episode_start,
    deterministic) -> (actions, state)``; a slot's state is reset where ``episode_start`` is true.

    :param observation_space: a flat Box
    :param action_space: a Box (Gaussian actions)
    :param lr_schedule: learning-rate schedule
    :param net_arch: any of the keys of :data:`DEFAULT_RECURRENT_NET_ARCH` (``pi``/``vf``: dense widths before the
        recurrent layer; ``pi_recurrent``/``vf_recurrent``: its width; ``pi_after``/``vf_after``: dense widths after)
    :param cell: ``"gru"`` (default) or ``"lstm"``
    :param activation_fn: activation of the dense layers
    :param sigma: fixed standard deviation of the Gaussian, > 0
    :param action_scale: factor on the tanh of the actor's output, > 0
    :param ortho_init: orthogonal initialisation (SB3's gains: sqrt(2) hidden, 0.01 action, 1 value)
    :param use_sde: must be False
    :param optimizer_class: optimiser (default Adam with SB3's eps 1e-5, fused)
    :param optimizer_kwargs: its keyword arguments
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: dict[str, Any] | None = None,
        cell: str = "gru",
        activation_fn: type[nn.Module] = nn.Tanh,
        sigma: float = DEFAULT_SIGMA,
        action_scale: float = 1.0,
        ortho_init: bool = True,
        use_sde: bool = False,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if cell not in CELLS:
            raise ValueError(f"cell must be one of {CELLS}, got {cell!r}")
        if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
            raise ValueError(f"RecurrentFormationPolicy needs a flat Box observation space, got {observation_space}")
        if not isinstance(action_space, spaces.Box):
            raise ValueError(f"RecurrentFormationPolicy needs a Box action space (Gaussian actions), got {action_space}")
        if use_sde:
            raise ValueError("RecurrentFormationPolicy does not support use_sde=True: its standard deviation is fixed")
        if not (math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"sigma must be a finite number > 0, got {sigma}")
        if not (math.isfinite(action_scale) and action_scale > 0):
            raise ValueError(f"action_scale must be a finite number > 0, got {action_scale}")
        unknown = set(net_arch or {}) - set(DEFAULT_RECURRENT_NET_ARCH)
        if unknown:
            raise ValueError(f"unknown net_arch keys {sorted(unknown)}; valid: {list(DEFAULT_RECURRENT_NET_ARCH)}")
        if optimizer_class is th.optim.Adam and optimizer_kwargs is None:
            optimizer_kwargs = {"eps": 1e-5, "fused": True}
        super().__init__(observation_space, action_space, optimizer_class=optimizer_class, optimizer_kwargs=optimizer_kwargs)
        self.features_extractor = self.make_features_extractor()  # flattens (and casts to float)
        self.net_arch = {**DEFAULT_RECURRENT_NET_ARCH, **(net_arch or {})}
        self.cell, self.activation_fn, self.ortho_init = cell, activation_fn, ortho_init
        self.sigma, self.action_scale = float(sigma), float(action_scale)
        arch, obs_dim, action_dim = self.net_arch, observation_space.shape[0], action_space.shape[0]
        self.actor = RecurrentHead(obs_dim, arch["pi"], arch["pi_recurrent"], arch["pi_after"], cell, activation_fn)
        self.critic = RecurrentHead(obs_dim, arch["vf"], arch["vf_recurrent"], arch["vf_after"], cell, activation_fn)
        self.action_net = nn.Linear(self.actor.output_dim, action_dim)
        self.value_net = nn.Linear(self.critic.output_dim, 1)
        self.log_std = nn.Parameter(th.full((action_dim,), math.log(self.sigma)), requires_grad=False)
        self.action_dist = DiagGaussianDistribution(action_dim)
        if ortho_init:
            for module, gain in ((self.actor, math.sqrt(2)), (self.critic, math.sqrt(2)), (self.action_net, 0.01)):
                module.apply(lambda layer, gain=gain: self.init_weights(layer, gain))
            self.value_net.apply(lambda layer: self.init_weights(layer, 1.0))
            for rnn in (self.actor.rnn, self.critic.rnn):
                for name, parameter in rnn.named_parameters():
                    if name.startswith("weight"):
                        nn.init.orthogonal_(parameter)
                    else:
                        nn.init.zeros_(parameter)
        trainable = [parameter for parameter in self.parameters() if parameter.requires_grad]
        self.optimizer = self.optimizer_class(trainable, lr=lr_schedule(1), **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.pop("normalize_images", None)  # observations are flat vectors
        data.update(
            lr_schedule=self._dummy_schedule,  # not needed to load the policy alone (as in SB3's ActorCriticPolicy)
            net_arch=self.net_arch,
            cell=self.cell,
            activation_fn=self.activation_fn,
            sigma=self.sigma,
            action_scale=self.action_scale,
            ortho_init=self.ortho_init,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def initial_state(self, n: int) -> RecurrentStates:
        """Zero actor and critic states for ``n`` slots."""
        return RecurrentStates(self.actor.initial_state(n, self.device), self.critic.initial_state(n, self.device))

    def _distribution(self, actor_output: th.Tensor) -> DiagGaussianDistribution:
        mean = self.action_scale * th.tanh(self.action_net(actor_output))
        return self.action_dist.proba_distribution(mean, self.log_std)

    def forward(
        self, obs: th.Tensor, states: RecurrentStates, episode_starts: th.Tensor, deterministic: bool = False
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RecurrentStates]:
        """One step for a batch of slots: states are reset where ``episode_starts`` is 1 before the step.

        :return: actions, values ``(n, 1)``, log-probabilities and the new states
        """
        states = states.masked(1.0 - episode_starts.float())
        features = self.extract_features(obs, self.features_extractor).unsqueeze(0)
        actor_output, pi_state = self.actor(features, states.pi)
        critic_output, vf_state = self.critic(features, states.vf)
        distribution = self._distribution(actor_output[0])
        actions = distribution.get_actions(deterministic=deterministic)
        return actions, self.value_net(critic_output[0]), distribution.log_prob(actions), RecurrentStates(pi_state, vf_state)

    def predict_values(self, obs: th.Tensor, vf_state: CellState, episode_starts: th.Tensor) -> th.Tensor:
        """Values ``(n, 1)`` of one step's observations from the critic's states (reset where ``episode_starts``)."""
        features = self.extract_features(obs, self.features_extractor).unsqueeze(0)
        critic_output, _ = self.critic(features, _kept(vf_state, 1.0 - episode_starts.float()))
        return self.value_net(critic_output[0])

    def evaluate_sequences(
        self, obs: th.Tensor, actions: th.Tensor, states: RecurrentStates
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Values, log-probabilities of ``actions`` and entropies over ``(L, B, ...)`` sequences from ``states``.

        The sequences must not cross an episode start (no reset happens inside them); padding after a sequence's end
        does not change its outputs (the cells are causal).
        """
        length, batch = obs.shape[:2]
        features = self.extract_features(obs.flatten(0, 1), self.features_extractor).unflatten(0, (length, batch))
        actor_output, _ = self.actor(features, states.pi)
        critic_output, _ = self.critic(features, states.vf)
        distribution = self._distribution(actor_output.flatten(0, 1))  # SB3 sums log-probabilities over dim 1
        log_prob = distribution.log_prob(actions.flatten(0, 1)).unflatten(0, (length, batch))
        entropy = distribution.entropy().unflatten(0, (length, batch))
        return self.value_net(critic_output).squeeze(-1), log_prob, entropy

    def _predict(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        raise NotImplementedError("a recurrent policy acts through predict(observation, state, episode_start)")

    def predict(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Actions for a batch of observations, carrying the actor's recurrent state (SB3's signature).

        :param observation: ``(n, obs_dim)`` observations (or one ``(obs_dim,)`` observation)
        :param state: the actor state returned by the previous call (``None``: zeros)
        :param episode_start: ``(n,)`` flags: reset these slots' states first (``None``: no reset)
        :param deterministic: return the mean action instead of a sample
        :return: actions clipped to the action space, and the new actor state (numpy arrays)
        """
        self.set_training_mode(False)
        observation = np.asarray(observation, dtype=np.float32)
        single = observation.ndim == 1
        batch = observation.reshape(-1, self.observation_space.shape[0])
        n = batch.shape[0]
        with th.no_grad():
            pi_state = (
                self.actor.initial_state(n, self.device)
                if state is None
                else tuple(th.as_tensor(np.asarray(array), dtype=th.float32, device=self.device) for array in state)
            )
            if episode_start is not None:
                pi_state = _kept(pi_state, 1.0 - th.as_tensor(episode_start, device=self.device).float().reshape(-1))
            features = self.extract_features(th.as_tensor(batch, device=self.device), self.features_extractor)
            actor_output, pi_state = self.actor(features.unsqueeze(0), pi_state)
            actions = self._distribution(actor_output[0]).get_actions(deterministic=deterministic)
        actions = np.clip(actions.cpu().numpy(), self.action_space.low, self.action_space.high)
        return (actions[0] if single else actions), tuple(tensor.cpu().numpy() for tensor in pi_state)


class SequenceBatch(NamedTuple):
    """A minibatch of whole sequences, ``(L, B, ...)``, padded after each sequence's end (``mask`` False there)."""

    observations: th.Tensor
    actions: th.Tensor
    old_values: th.Tensor
    old_log_prob: th.Tensor
    advantages: th.Tensor
    returns: th.Tensor
    mask: th.Tensor
    states: RecurrentStates


class SequenceLayout(NamedTuple):
    """How a rollout of ``T`` steps and ``N`` slots splits into sequences (slot-major: slot 0's sequences first).

    :param sequence: ``(N * T,)`` sequence of each step, steps in slot-major order (index ``slot * T + t``)
    :param position: ``(N * T,)`` position of each step within its sequence
    :param lengths: ``(S,)`` sequence lengths
    :param slots: ``(S,)`` slot of each sequence
    :param first_steps: ``(S,)`` time step at which each sequence starts
    """

    sequence: np.ndarray
    position: np.ndarray
    lengths: np.ndarray
    slots: np.ndarray
    first_steps: np.ndarray


def sequence_layout(episode_starts: np.ndarray, max_length: int | None = None) -> SequenceLayout:
    """Cut each slot's steps into sequences at the rollout's start, at every episode start and, with ``max_length``,
    every ``max_length`` steps of the rollout (t = 0, max_length, 2 max_length, ...).

    :param episode_starts: ``(T, N)`` flags: the step is the first of an episode
    :param max_length: longest sequence (``None``: the rollout's length)
    """
    steps = episode_starts.shape[0]
    starts = episode_starts.astype(bool).T.copy()  # (N, T), slot-major
    starts[:, :: max_length or steps] = True
    flat = starts.reshape(-1)
    sequence = np.cumsum(flat) - 1
    first = np.flatnonzero(flat)
    lengths = np.diff(np.append(first, flat.size))
    position = np.arange(flat.size) - first[sequence]
    return SequenceLayout(sequence, position, lengths, first // steps, first % steps)


class RecurrentRolloutBuffer(RolloutBuffer):
    """SB3's ``RolloutBuffer`` plus the hidden states each step started from, served as sequence minibatches.

    Arguments are those of :class:`~stable_baselines3.common.buffers.RolloutBuffer`; ``max_sequence_length`` cuts the
    sequences (see :func:`sequence_layout`).
    """

    max_sequence_length: int | None = None

    def reset(self) -> None:
        super().reset()
        self.step_states: list[RecurrentStates] = []

    def add_states(self, states: RecurrentStates) -> None:
        """Store the states (already reset where an episode starts) from which the slots act at the next ``add``."""
        self.step_states.append(states)

    def sequence_batches(self, batch_size: int) -> Generator[SequenceBatch, None, None]:
        """Minibatches of whole sequences in random order, each about ``batch_size`` steps (at least one sequence).

        A sequence is the steps of one slot from the rollout's start, an episode start or a multiple of
        ``max_sequence_length`` to the step before the next one, so no minibatch row mixes slots or episodes. It is
        replayed from the states stored for its first step.
        """
        assert self.full and len(self.step_states) == self.buffer_size, "fill the buffer (and its states) first"
        layout = sequence_layout(self.episode_starts, self.max_sequence_length)
        count, longest = len(layout.lengths), int(layout.lengths.max())
        mask = np.zeros((longest, count), dtype=bool)
        mask[layout.position, layout.sequence] = True

        def padded(array: np.ndarray) -> th.Tensor:
            flat = array.swapaxes(0, 1).reshape(self.n_envs * self.buffer_size, *array.shape[2:])
            out = np.zeros((longest, count, *array.shape[2:]), dtype=np.float32)
            out[layout.position, layout.sequence] = flat
            return self.to_torch(out)

        observations, actions = padded(self.observations), padded(self.actions)
        values, log_probs = padded(self.values), padded(self.log_probs)
        advantages, returns = padded(self.advantages), padded(self.returns)
        steps, slots = (th.as_tensor(index, device=self.device) for index in (layout.first_steps, layout.slots))

        def first_states(part: int, component: int) -> th.Tensor:
            history = th.stack([states[part][component] for states in self.step_states])  # (T, 1, N, hidden)
            return history[steps, 0, slots].unsqueeze(0)  # (1, S, hidden)

        states = RecurrentStates(
            *(tuple(first_states(part, component) for component in range(len(self.step_states[0][part]))) for part in (0, 1))
        )
        order = np.random.permutation(count)  # noqa: NPY002 - SB3 seeds numpy's global generator (set_random_seed)
        batch_of = (np.cumsum(layout.lengths[order]) - 1) // batch_size
        for batch in np.unique(batch_of):
            chosen = order[batch_of == batch]
            rows = int(layout.lengths[chosen].max())
            index = th.as_tensor(chosen, device=self.device)
            yield SequenceBatch(
                observations[:rows, index],
                actions[:rows, index],
                values[:rows, index],
                log_probs[:rows, index],
                advantages[:rows, index],
                returns[:rows, index],
                self.to_torch(mask[:rows, chosen]).bool(),
                states.select(index),
            )


def _masked_mean(values: th.Tensor, mask: th.Tensor) -> th.Tensor:
    return values[mask].mean()


class RecurrentFormationPPO(PPO):
    """SB3's ``PPO`` for :class:`RecurrentFormationPolicy`: rollouts carry hidden states, updates replay sequences.

    Construction, ``learn``, callbacks, logging, ``save`` and ``load`` are SB3's. Differences from ``PPO``:

    - Each slot's actor and critic states are carried from step to step and reset when the slot's episode starts;
      time-outs are bootstrapped with the critic's state after the last real step.
    - The update cuts every slot's rollout into sequences at episode starts and every ``max_sequence_length`` steps,
      and forms minibatches of about ``batch_size`` steps of whole sequences; each sequence is replayed from the
      states stored for its first step during the rollout (zeros at an episode start); losses are means over the real
      (unpadded) steps; advantages are normalised per minibatch over those steps.

    :param policy: :class:`RecurrentFormationPolicy` (the default)
    :param env: the environment
    :param max_sequence_length: longest sequence replayed in an update (``None``: up to the rollout's length)
    :param kwargs: SB3 ``PPO`` arguments
    """

    policy: RecurrentFormationPolicy
    rollout_buffer: RecurrentRolloutBuffer

    def __init__(
        self,
        policy: type[RecurrentFormationPolicy] | str = RecurrentFormationPolicy,
        env: Any = None,
        max_sequence_length: int | None = DEFAULT_MAX_SEQUENCE_LENGTH,
        **kwargs: Any,
    ) -> None:
        if max_sequence_length is not None and not (isinstance(max_sequence_length, int) and max_sequence_length >= 1):
            raise ValueError(f"max_sequence_length must be None or an integer >= 1, got {max_sequence_length!r}")
        self.max_sequence_length = max_sequence_length
        if policy == "RecurrentFormationPolicy":
            policy = RecurrentFormationPolicy
        if not (isinstance(policy, type) and issubclass(policy, RecurrentFormationPolicy)):
            raise ValueError(f"RecurrentFormationPPO trains a RecurrentFormationPolicy, got {policy!r}")
        if kwargs.get("rollout_buffer_class") not in (None, RecurrentRolloutBuffer):
            raise ValueError("RecurrentFormationPPO needs its RecurrentRolloutBuffer")
        kwargs["rollout_buffer_class"] = RecurrentRolloutBuffer
        super().__init__(policy, env, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.rollout_buffer.max_sequence_length = self.max_sequence_length
        self._last_states = self.policy.initial_state(self.n_envs)
        self._last_episode_starts = np.ones(self.n_envs, dtype=bool)  # zero states: a loaded model starts afresh

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_last_states"]

    def collect_rollouts(
        self, env: VecEnv, callback: BaseCallback, rollout_buffer: RolloutBuffer, n_rollout_steps: int
    ) -> bool:
        """SB3's rollout loop with hidden states: see the class docstring."""
        assert self._last_obs is not None, "No previous observation was provided"
        assert isinstance(rollout_buffer, RecurrentRolloutBuffer)
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        callback.on_rollout_start()
        while n_steps < n_rollout_steps:
            with th.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)
                starts = th.as_tensor(self._last_episode_starts, dtype=th.float32, device=self.device)
                entering = self._last_states.masked(1.0 - starts)  # reset where an episode starts
                actions, values, log_probs, self._last_states = self.policy(obs_tensor, entering, starts)
            actions = actions.cpu().numpy()
            clipped_actions = np.clip(actions, self.action_space.low, self.action_space.high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            timeouts = [
                index
                for index, done in enumerate(dones)
                if done and infos[index].get("terminal_observation") is not None and infos[index].get("TimeLimit.truncated")
            ]
            if timeouts:  # bootstrap from the critic's state after the last real step (see SB3 issue #633)
                terminal = obs_as_tensor(np.stack([infos[index]["terminal_observation"] for index in timeouts]), self.device)
                rows = th.as_tensor(timeouts, device=self.device)
                with th.no_grad():
                    terminal_values = self.policy.predict_values(
                        terminal, self._last_states.select(rows).vf, th.zeros(len(timeouts), device=self.device)
                    )
                rewards[timeouts] += self.gamma * terminal_values.squeeze(-1).cpu().numpy()
            rollout_buffer.add_states(entering)
            rollout_buffer.add(self._last_obs, actions, rewards, self._last_episode_starts, values, log_probs)
            self._last_obs = new_obs
            self._last_episode_starts = dones
        with th.no_grad():
            starts = th.as_tensor(dones, dtype=th.float32, device=self.device)
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device), self._last_states.vf, starts)
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """PPO's clipped update over minibatches of whole sequences (see the class docstring)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)
        clip_range_vf = None if self.clip_range_vf is None else self.clip_range_vf(self._current_progress_remaining)
        entropy_losses, pg_losses, value_losses, clip_fractions = [], [], [], []
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for batch in self.rollout_buffer.sequence_batches(self.batch_size):
                mask = batch.mask
                values, log_prob, entropy = self.policy.evaluate_sequences(batch.observations, batch.actions, batch.states)
                advantages = batch.advantages
                if self.normalize_advantage and int(mask.sum()) > 1:
                    real = advantages[mask]
                    advantages = (advantages - real.mean()) / (real.std() + 1e-8)
                ratio = th.exp(log_prob - batch.old_log_prob)
                policy_loss_1 = advantages * ratio
                policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
                policy_loss = -_masked_mean(th.min(policy_loss_1, policy_loss_2), mask)
                pg_losses.append(policy_loss.item())
                clip_fractions.append(_masked_mean((th.abs(ratio - 1) > clip_range).float(), mask).item())
                if clip_range_vf is not None:
                    values = batch.old_values + th.clamp(values - batch.old_values, -clip_range_vf, clip_range_vf)
                value_loss = _masked_mean((batch.returns - values) ** 2, mask)
                value_losses.append(value_loss.item())
                entropy_loss = -_masked_mean(entropy, mask)
                entropy_losses.append(entropy_loss.item())
                loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
                with th.no_grad():
                    log_ratio = log_prob - batch.old_log_prob
                    approx_kl_div = _masked_mean(th.exp(log_ratio) - 1 - log_ratio, mask).cpu().numpy()
                    approx_kl_divs.append(approx_kl_div)
                if self.target_kl is not None and approx_kl_div > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl_div:.2f}")
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
            self._n_updates += 1
            if not continue_training:
                break
        explained_var = explained_variance(self.rollout_buffer.values.flatten(), self.rollout_buffer.returns.flatten())
        self.logger.record("train/entropy_loss", np.mean(entropy_losses))
        self.logger.record("train/policy_gradient_loss", np.mean(pg_losses))
        self.logger.record("train/value_loss", np.mean(value_losses))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(clip_fractions))
        self.logger.record("train/loss", loss.item())
        self.logger.record("train/explained_variance", explained_var)
        self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)
