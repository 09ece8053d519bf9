"""The recurrent actor-critic of thesis chapter 5 (figs 5.1 and 5.2): GRU or LSTM heads, fixed sigma."""

from __future__ import annotations

import math
from typing import Any, NamedTuple, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_formation.sb3.networks import (
    ModeOnChange,
    check_action_distribution,
    default_optimizer_kwargs,
    gaussian_actions,
    mlp,
)
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

#: The most values a message may hold (``message_size``): a bound on a radio's payload, 1 KiB of float32 values.
MAX_MESSAGE_SIZE = 256
#: A recurrent head's state: ``(h,)`` for a GRU, ``(h, c)`` for an LSTM; each ``(1, n, hidden)``.
CellState = tuple[th.Tensor, ...]


class RecurrentStates(NamedTuple):
    """Hidden states of the actor (``pi``) and of the critic (``vf``) for a batch of slots, and the messages each slot
    sent at its last step (``(n, message_size)``; ``(n, 0)`` for a policy that sends none)."""

    pi: CellState
    vf: CellState
    messages: th.Tensor

    def select(self, rows: th.Tensor | np.ndarray | slice) -> RecurrentStates:
        """The states of some slots (rows of the batch dimension)."""
        pi, vf = (tuple(tensor[:, rows] for tensor in state) for state in (self.pi, self.vf))
        return RecurrentStates(pi, vf, self.messages[rows])

    def masked(self, keep: th.Tensor) -> RecurrentStates:
        """Every state and message multiplied by ``keep`` (``(n,)``, 0 to reset a slot, 1 to keep it)."""
        return RecurrentStates(_kept(self.pi, keep), _kept(self.vf, keep), self.messages * keep.float().view(-1, 1))


def _kept(state: CellState, keep: th.Tensor) -> CellState:
    """``state`` with slot i's rows multiplied by ``keep[i]`` (0 resets the slot, 1 keeps it)."""
    factor = keep.float().view(1, -1, 1)
    return tuple(tensor * factor for tensor in state)


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
        self.before, width = mlp(input_dim, before, activation_fn)
        self.rnn = (nn.GRU if cell == "gru" else nn.LSTM)(width, hidden)
        self.after, self.output_dim = mlp(hidden, after, activation_fn)
        self.cell, self.hidden = cell, hidden

    def initial_state(self, n: int, device: th.device) -> CellState:
        """Zero states for ``n`` slots."""
        count = 1 if self.cell == "gru" else 2
        return tuple(th.zeros(1, n, self.hidden, device=device) for _ in range(count))

    def forward(self, inputs: th.Tensor, state: CellState) -> tuple[th.Tensor, CellState]:
        """Run over ``(L, B, input_dim)`` sequences from ``state``; return ``(L, B, output_dim)`` and the final state."""
        outputs, final = self.rnn(self.before(inputs), state[0] if self.cell == "gru" else state)
        return self.after(outputs), (final,) if self.cell == "gru" else tuple(final)


class RecurrentFormationPolicy(ModeOnChange, BasePolicy):
    """Recurrent actor-critic of thesis chapter 5 (figs 5.1 and 5.2) for :class:`RecurrentFormationPPO`.

    The actor and the critic each have their own recurrent state. The action distribution is a diagonal Gaussian with
    mean ``action_scale * tanh(action_net(actor output))`` and a fixed standard deviation ``sigma`` (not trained; with
    ``learn_sigma`` a learned state-independent log-std starting at log(sigma)).
    :meth:`predict` has SB3's signature with the actor's state: ``predict(observation, state, episode_start,
    deterministic) -> (actions, state)``; a slot's state is reset where ``episode_start`` is true.

    **Messages** (``message_size`` M > 0, ``docs/training.md`` "Memory and messages"): every step each agent sends its
    two ring neighbours the vector ``tanh(message_net(actor output))`` (M values in [-1, 1]), which they receive at
    their next step, appended to their observation: [own observation, preceding neighbour's message, succeeding
    neighbour's]; zeros at an episode's start. The message is differentiable: an update replays whole teams' sequences
    (``neighbours`` gives each row's neighbours' rows), so a neighbour's loss trains the sender. An agent's action
    depends only on its own observations and the messages its neighbours sent it, one step late. With
    ``memory=False`` the recurrent layers start every step from zeros: an ablation whose actions depend on the current
    observation and messages only.

    :param observation_space: a flat Box
    :param action_space: a Box (Gaussian actions)
    :param lr_schedule: learning-rate schedule
    :param net_arch: any of the keys of :data:`DEFAULT_RECURRENT_NET_ARCH` (``pi``/``vf``: dense widths before the
        recurrent layer; ``pi_recurrent``/``vf_recurrent``: its width; ``pi_after``/``vf_after``: dense widths after)
    :param cell: ``"gru"`` (default) or ``"lstm"``
    :param activation_fn: activation of the dense layers
    :param sigma: standard deviation of the Gaussian, > 0 (the initial one with ``learn_sigma``)
    :param learn_sigma: train the log-std instead of keeping sigma fixed
    :param action_scale: factor on the tanh of the actor's output, > 0
    :param ortho_init: orthogonal initialisation (SB3's gains: sqrt(2) hidden, 0.01 action, 1 value)
    :param message_size: M, values of the message each agent sends its ring neighbours every step (0: none)
    :param memory: carry the recurrent state from step to step (False: start every step from zeros)
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
        learn_sigma: bool = False,
        action_scale: float = 1.0,
        ortho_init: bool = True,
        message_size: int = 0,
        memory: bool = True,
        use_sde: bool = False,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if cell not in CELLS:
            raise ValueError(f"cell must be one of {CELLS}, got {cell!r}")
        if not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
            raise ValueError(f"RecurrentFormationPolicy needs a flat Box observation space, got {observation_space}")
        check_action_distribution("RecurrentFormationPolicy", action_space, sigma, action_scale, use_sde)
        if not (
            isinstance(message_size, int) and not isinstance(message_size, bool) and 0 <= message_size <= MAX_MESSAGE_SIZE
        ):
            raise ValueError(f"message_size must be an integer in [0, {MAX_MESSAGE_SIZE}], got {message_size!r}")
        if not isinstance(memory, bool):
            raise ValueError(f"memory must be true or false, got {memory!r}")
        unknown = set(net_arch or {}) - set(DEFAULT_RECURRENT_NET_ARCH)
        if unknown:
            raise ValueError(f"unknown net_arch keys {sorted(unknown)}; valid: {list(DEFAULT_RECURRENT_NET_ARCH)}")
        optimizer_kwargs = default_optimizer_kwargs(optimizer_class, optimizer_kwargs)
        super().__init__(observation_space, action_space, optimizer_class=optimizer_class, optimizer_kwargs=optimizer_kwargs)
        self.features_extractor = self.make_features_extractor()  # flattens (and casts to float)
        self.net_arch = {**DEFAULT_RECURRENT_NET_ARCH, **(net_arch or {})}
        self.cell, self.activation_fn, self.ortho_init = cell, activation_fn, ortho_init
        self.sigma, self.learn_sigma, self.action_scale = float(sigma), bool(learn_sigma), float(action_scale)
        self.message_size, self.memory = message_size, memory
        action_shape = cast(spaces.Box, action_space).shape  # checked above
        arch, action_dim = self.net_arch, action_shape[0]
        inputs = observation_space.shape[0] + 2 * message_size  # the own observation, then the neighbours' messages
        self.actor = RecurrentHead(inputs, arch["pi"], arch["pi_recurrent"], arch["pi_after"], cell, activation_fn)
        self.critic = RecurrentHead(inputs, arch["vf"], arch["vf_recurrent"], arch["vf_after"], cell, activation_fn)
        self.action_net = nn.Linear(self.actor.output_dim, action_dim)
        self.message_net = nn.Linear(self.actor.output_dim, message_size) if message_size else None
        self.value_net = nn.Linear(self.critic.output_dim, 1)
        self.log_std = nn.Parameter(th.full((action_dim,), math.log(self.sigma)), requires_grad=self.learn_sigma)
        self.action_dist = DiagGaussianDistribution(action_dim)
        if ortho_init:
            heads = [(self.actor, math.sqrt(2)), (self.critic, math.sqrt(2)), (self.action_net, 0.01)]
            for module, gain in heads + ([(self.message_net, 1.0)] if self.message_net is not None else []):
                module.apply(lambda layer, gain=gain: self.init_weights(layer, gain))  # type: ignore[misc]  # mypy cannot type a lambda's default
            self.value_net.apply(lambda layer: self.init_weights(layer, 1.0))
            for rnn in (self.actor.rnn, self.critic.rnn):
                for name, parameter in rnn.named_parameters():
                    if name.startswith("weight"):
                        nn.init.orthogonal_(parameter)
                    else:
                        nn.init.zeros_(parameter)
        trainable = [parameter for parameter in self.parameters() if parameter.requires_grad]
        # optimizer_class is an Optimizer that takes lr (Adam by default), as SB3's policies call it
        self.optimizer = self.optimizer_class(trainable, lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.pop("normalize_images", None)  # observations are flat vectors
        data.update(
            lr_schedule=self._dummy_schedule,  # not needed to load the policy alone (as in SB3's ActorCriticPolicy)
            net_arch=self.net_arch,
            cell=self.cell,
            activation_fn=self.activation_fn,
            sigma=self.sigma,
            learn_sigma=self.learn_sigma,
            action_scale=self.action_scale,
            ortho_init=self.ortho_init,
            message_size=self.message_size,
            memory=self.memory,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def initial_state(self, n: int) -> RecurrentStates:
        """Zero actor and critic states, and zero messages, for ``n`` slots."""
        messages = th.zeros(n, self.message_size, device=self.device)
        return RecurrentStates(self.actor.initial_state(n, self.device), self.critic.initial_state(n, self.device), messages)

    def entering(self, states: RecurrentStates, episode_starts: th.Tensor) -> RecurrentStates:
        """The states the slots act from: reset where ``episode_starts`` is 1 (and every step without memory)."""
        states = states.masked(1.0 - episode_starts.float())
        if self.memory:
            return states
        n = len(states.messages)
        return RecurrentStates(
            self.actor.initial_state(n, self.device), self.critic.initial_state(n, self.device), states.messages
        )

    def received(self, messages: th.Tensor, neighbours: th.Tensor | np.ndarray | None) -> th.Tensor | None:
        """What each row receives: its preceding then its succeeding neighbour's message, ``(n, 2 M)`` (``None``
        without messages).

        :param messages: ``(n, M)`` the messages the rows sent at their last step
        :param neighbours: ``(n, 2)`` each row's neighbours' rows (:func:`~sb3_formation.env.geometry.ring_rows`)
        :raises ValueError: a policy with messages and no ``neighbours``
        """
        if not self.message_size:
            return None
        if neighbours is None:
            raise ValueError("a policy with messages needs each row's ring neighbours (neighbours=ring_rows(team_sizes))")
        return messages[th.as_tensor(neighbours, device=messages.device)].flatten(1)

    def _inputs(self, features: th.Tensor, received: th.Tensor | None) -> th.Tensor:
        return features if received is None else th.cat([features, received], dim=-1)

    def _message(self, actor_output: th.Tensor) -> th.Tensor:
        """The message each row sends (``(..., M)``, in [-1, 1])."""
        if self.message_net is None:
            return actor_output.new_zeros(*actor_output.shape[:-1], 0)
        return th.tanh(self.message_net(actor_output))

    def _distribution(self, actor_output: th.Tensor) -> DiagGaussianDistribution:
        mean = self.action_scale * th.tanh(self.action_net(actor_output))
        return gaussian_actions(self.action_dist, mean, self.log_std)

    def forward(
        self,
        obs: th.Tensor,
        states: RecurrentStates,
        episode_starts: th.Tensor,
        deterministic: bool = False,
        neighbours: th.Tensor | np.ndarray | None = None,
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, RecurrentStates]:
        """One step for a batch of slots: states are reset where ``episode_starts`` is 1 before the step.

        :param neighbours: ``(n, 2)`` each slot's ring neighbours' slots (a policy with messages only)
        :return: actions, values ``(n, 1)``, log-probabilities and the new states (with the messages sent)
        """
        states = self.entering(states, episode_starts)
        features = self.extract_features(obs, self.features_extractor)
        inputs = self._inputs(features, self.received(states.messages, neighbours)).unsqueeze(0)
        actor_output, pi_state = self.actor(inputs, states.pi)
        critic_output, vf_state = self.critic(inputs, states.vf)
        distribution = self._distribution(actor_output[0])
        actions = distribution.get_actions(deterministic=deterministic)
        new_states = RecurrentStates(pi_state, vf_state, self._message(actor_output[0]))
        return actions, self.value_net(critic_output[0]), distribution.log_prob(actions), new_states

    def predict_values(
        self, obs: th.Tensor, vf_state: CellState, episode_starts: th.Tensor, received: th.Tensor | None = None
    ) -> th.Tensor:
        """Values ``(n, 1)`` of one step's observations from the critic's states (reset where ``episode_starts``, and
        always without memory) and the messages the rows received (:meth:`received`; ``None`` without messages)."""
        keep = (1.0 - episode_starts.float()) * float(self.memory)
        features = self._inputs(self.extract_features(obs, self.features_extractor), received).unsqueeze(0)
        critic_output, _ = self.critic(features, _kept(vf_state, keep))
        return self.value_net(critic_output[0])

    def evaluate_sequences(
        self, obs: th.Tensor, actions: th.Tensor, states: RecurrentStates, neighbours: th.Tensor | None = None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Values, log-probabilities of ``actions`` and entropies over ``(L, B, ...)`` sequences from ``states``.

        The sequences must not cross an episode start (no reset happens inside them); padding after a sequence's end
        does not change its outputs (the cells are causal). With messages the batch holds whole teams' sequences of
        equal length, ``neighbours`` ``(B, 2)`` naming each column's neighbours' columns, and each step's messages
        are recomputed from the previous step's actor outputs (the first step's come from ``states``), so gradients
        flow from a receiver's loss into the sender.
        """
        length, batch = obs.shape[:2]
        features = self.extract_features(obs.flatten(0, 1), self.features_extractor).unflatten(0, (length, batch))
        if self.memory and not self.message_size:  # one call of the cell over the whole sequences
            actor_output, _ = self.actor(features, states.pi)
            critic_inputs, vf_state = features, states.vf
        else:
            actor_output, received = self._replay_actor(features, states, neighbours)
            critic_inputs = self._inputs(features, received)
            vf_state = states.vf
            if not self.memory:  # every step from zeros: the steps as one batch of single steps
                critic_inputs, vf_state = (
                    critic_inputs.flatten(0, 1).unsqueeze(0),
                    self.critic.initial_state(length * batch, self.device),
                )
        critic_output, _ = self.critic(critic_inputs, vf_state)
        distribution = self._distribution(actor_output.flatten(0, 1))  # SB3 sums log-probabilities over dim 1
        log_prob = distribution.log_prob(actions.flatten(0, 1)).unflatten(0, (length, batch))
        entropy = cast(th.Tensor, distribution.entropy()).unflatten(0, (length, batch))  # a Gaussian's is never None
        return self.value_net(critic_output).reshape(length, batch), log_prob, entropy

    def _replay_actor(
        self, features: th.Tensor, states: RecurrentStates, neighbours: th.Tensor | None
    ) -> tuple[th.Tensor, th.Tensor | None]:
        """The actor over ``(L, B, ...)`` sequences one step at a time, passing each step's messages to the next:
        its outputs ``(L, B, ...)`` and what each column received (detached, for the critic; ``None`` without
        messages)."""
        pi_state, messages = states.pi, states.messages
        outputs, received_steps = [], []
        for step in features:
            received = self.received(messages, neighbours)
            if not self.memory:
                pi_state = self.actor.initial_state(len(step), self.device)
            output, pi_state = self.actor(self._inputs(step, received).unsqueeze(0), pi_state)
            outputs.append(output[0])
            messages = self._message(output[0])
            if received is not None:
                received_steps.append(received.detach())
        return th.stack(outputs), (th.stack(received_steps) if received_steps else None)

    def _predict(self, observation: th.Tensor | dict[str, th.Tensor], deterministic: bool = False) -> th.Tensor:
        raise NotImplementedError("a recurrent policy acts through predict(observation, state, episode_start)")

    def predict(  # type: ignore[override]  # flat Box observations only (checked in __init__), not dicts
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
        neighbours: np.ndarray | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
        """Actions for a batch of observations, carrying the actor's recurrent state (SB3's signature).

        :param observation: ``(n, obs_dim)`` observations (or one ``(obs_dim,)`` observation)
        :param state: the state returned by the previous call (``None``: zeros): the actor's cell state, then (with
            messages) the ``(n, M)`` messages the rows sent
        :param episode_start: ``(n,)`` flags: reset these slots' states first (``None``: no reset)
        :param deterministic: return the mean action instead of a sample
        :param neighbours: ``(n, 2)`` each row's ring neighbours' rows (a policy with messages only)
        :return: actions clipped to the action space, and the new state (numpy arrays)
        """
        observation = np.asarray(observation, dtype=np.float32)
        single = observation.ndim == 1
        n = observation.reshape(-1, cast(spaces.Box, self.observation_space).shape[0]).shape[0]
        parts = len(self.actor.initial_state(1, self.device))
        pi_state = None if state is None else tuple(state[:parts])
        received = None
        if self.message_size:
            if neighbours is None:
                raise ValueError("a policy with messages needs each row's ring neighbours (neighbours=ring_rows(team_sizes))")
            sent = np.zeros((n, self.message_size), np.float32) if state is None else np.asarray(state[parts], np.float32)
            if episode_start is not None:
                sent = sent * (1.0 - np.asarray(episode_start, np.float32).reshape(-1, 1))
            received = sent[np.asarray(neighbours)].reshape(n, -1)
        actions, pi_state, sent = self.actor_step(observation, pi_state, episode_start, received, deterministic)
        return (actions[0] if single else actions), (*pi_state, *((sent,) if self.message_size else ()))

    def actor_step(
        self,
        observation: np.ndarray,
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        received: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
        """One step of the actor for rows of any agents, given the messages they received: the policy contract's agent
        call (:meth:`~sb3_formation.sb3.trained.TrainedPolicy.agent_step`) on normalised observations.

        :param observation: ``(n, obs_dim)`` observations
        :param state: the actor's cell state the previous call returned (``None``: zeros)
        :param episode_start: ``(n,)`` flags: reset these rows' states first (``None``: no reset)
        :param received: ``(n, 2 M)`` what each row's preceding and succeeding neighbours sent (``None``: zeros)
        :param deterministic: return the mean action instead of a sample
        :return: actions clipped to the action space, the actor's next cell state and the ``(n, M)`` messages sent
        """
        self.set_training_mode(False)
        batch = np.asarray(observation, dtype=np.float32).reshape(-1, cast(spaces.Box, self.observation_space).shape[0])
        n = batch.shape[0]
        actions: th.Tensor | np.ndarray  # a tensor, then its clipped numpy values
        with th.no_grad():
            pi_state = self.actor.initial_state(n, self.device)
            if state is not None:
                pi_state = tuple(th.as_tensor(np.asarray(array), dtype=th.float32, device=self.device) for array in state)
            if episode_start is not None:
                pi_state = _kept(pi_state, 1.0 - th.as_tensor(episode_start).float().reshape(-1).to(self.device))
            if not self.memory:
                pi_state = self.actor.initial_state(n, self.device)
            features = self.extract_features(th.as_tensor(batch, device=self.device), self.features_extractor)
            if self.message_size:
                messages = np.zeros((n, 2 * self.message_size), np.float32) if received is None else received
                features = self._inputs(features, th.as_tensor(messages, dtype=th.float32, device=self.device))
            actor_output, pi_state = self.actor(features.unsqueeze(0), pi_state)
            actions = self._distribution(actor_output[0]).get_actions(deterministic=deterministic)
            sent = self._message(actor_output[0])
        box = cast(spaces.Box, self.action_space)  # checked in __init__
        actions = cast(np.ndarray, np.clip(actions.cpu().numpy(), box.low, box.high))
        return actions, tuple(tensor.cpu().numpy() for tensor in pi_state), sent.cpu().numpy()
