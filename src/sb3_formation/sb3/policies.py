"""The thesis's actor-critic network as a Stable-Baselines3 policy (thesis 4.1.2, 4.3, 5.1.2).

``PPO(FormationPolicy, env, policy_kwargs=dict(...))`` works like any SB3 policy:

- Actor: 512 -> 256 -> 2, tanh on every layer including the output, whose mean is multiplied by
  ``action_scale`` (0.01 for the chapter-4 individual reward scheme, thesis 4.1.2).
- Gaussian exploration with a fixed, not learned, standard deviation ``sigma`` (0.7, thesis 4.3), or, with
  ``learn_sigma``, a learned state-independent log-std starting at log(sigma) (SB3's own default).
- Critic: 512 -> 512 -> 512 -> 1 (tanh, linear output); or, with ``team_size=n``, the team critic
  of thesis fig. 4.3: two 512-wide layers applied to each of the team's n agents with shared
  weights, the mean over the agents, then 512 -> 512 -> 1 (centralised training, decentralised
  execution: the actor sees only the agent's own observation).
- Orthogonal initialisation of every layer with SB3's gains (sqrt(2) hidden, 0.01 action, 1 value).
"""

from __future__ import annotations

import math
import numbers
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import get_device
from torch import nn

from sb3_formation.sb3.networks import (
    ModeOnChange,
    check_action_distribution,
    default_optimizer_kwargs,
    gaussian_actions,
    mlp,
)

#: Layer widths as SB3 writes them: a list shared by actor and critic, or ``dict(pi=[...], vf=[...])``.
NetArch = list[int] | dict[str, list[int]]

#: Thesis fig. 4.1 and 4.2: actor 512 -> 256 (-> 2), individual critic 512 -> 512 -> 512 (-> 1).
DEFAULT_NET_ARCH: dict[str, list[int]] = dict(pi=[512, 256], vf=[512, 512, 512])
#: Thesis fig. 4.3: team critic with four 512-wide tanh layers (-> 1), the first two applied per agent.
DEFAULT_TEAM_NET_ARCH: dict[str, list[int]] = dict(pi=[512, 256], vf=[512, 512, 512, 512])
#: Thesis fig. 4.3: "the output of the second layer is averaged for each agent".
TEAM_EMBED_LAYERS = 2
#: Thesis 4.3: sigma = 0.7.
DEFAULT_SIGMA = 0.7


def _split_net_arch(net_arch: NetArch) -> tuple[list[int], list[int]]:
    """The actor's and the critic's hidden widths, read as SB3's :class:`MlpExtractor` reads them."""
    if isinstance(net_arch, dict):
        return list(net_arch.get("pi", [])), list(net_arch.get("vf", []))
    return list(net_arch), list(net_arch)


class TeamCriticExtractor(nn.Module):
    """Actor and team-critic latent networks with the interface of SB3's :class:`MlpExtractor`.

    Each slot's features are ``[own observation (D values), observation of team agent 0, ..., of agent n-1]``,
    length ``D * (1 + n)``. The actor reads only the first ``D`` values. The critic embeds each of the n team
    observations with the same MLP (the first ``TEAM_EMBED_LAYERS`` widths of ``net_arch["vf"]``), takes the
    mean over the agents (so the value does not depend on their order) and passes it through the remaining
    widths; it ignores the leading own block (the agent's observation is also among the team's). SB3's
    ``value_net`` then maps the critic latent to the value. Every slot carries its whole team, so PPO's
    shuffled minibatches need no special handling.

    :param feature_dim: length of a slot's features, ``D * (1 + team_size)``
    :param net_arch: hidden widths, as for :class:`MlpExtractor`; ``vf`` needs at least ``TEAM_EMBED_LAYERS``
    :param activation_fn: activation after every hidden layer
    :param team_size: number n of agents whose observations the critic sees
    :param device: PyTorch device
    """

    def __init__(
        self,
        feature_dim: int,
        net_arch: NetArch,
        activation_fn: type[nn.Module],
        team_size: int,
        device: th.device | str = "auto",
    ) -> None:
        super().__init__()
        if team_size < 1:
            raise ValueError(f"team_size must be a positive int, got {team_size}")
        if feature_dim % (1 + team_size) != 0:
            raise ValueError(
                f"team critic: observation length {feature_dim} is not divisible by 1 + team_size = {1 + team_size}; "
                "each slot must hold its own observation followed by the observations of the team's agents"
            )
        pi_widths, vf_widths = _split_net_arch(net_arch)
        if len(vf_widths) < TEAM_EMBED_LAYERS:
            raise ValueError(
                f"team critic: net_arch['vf'] must list at least {TEAM_EMBED_LAYERS} widths "
                f"(the first {TEAM_EMBED_LAYERS} are applied per agent), got {vf_widths}"
            )
        device = get_device(device)
        self.team_size = team_size
        self.obs_dim = feature_dim // (1 + team_size)
        self.policy_net, self.latent_dim_pi = mlp(self.obs_dim, pi_widths, activation_fn)
        self.agent_net, embed_dim = mlp(self.obs_dim, vf_widths[:TEAM_EMBED_LAYERS], activation_fn)
        self.team_net, self.latent_dim_vf = mlp(embed_dim, vf_widths[TEAM_EMBED_LAYERS:], activation_fn)
        self.to(device)

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """:return: the actor's and the critic's latent codes."""
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:
        """The actor latent from the slot's own observation (the first ``D`` values) only."""
        return self.policy_net(features[..., : self.obs_dim])

    def forward_critic(self, features: th.Tensor) -> th.Tensor:
        """The critic latent: per-agent embedding of the n team observations, mean over agents, then the head."""
        team = features[..., self.obs_dim :].unflatten(-1, (self.team_size, self.obs_dim))
        return self.team_net(self.agent_net(team).mean(dim=-2))


class FormationPolicy(ModeOnChange, ActorCriticPolicy):
    """SB3 actor-critic policy of the thesis (4.1.2, 5.1.2): tanh MLPs, bounded action mean, fixed sigma.

    The action distribution is a diagonal Gaussian with mean ``action_scale * tanh(action_net(latent_pi))`` and
    standard deviation ``sigma``. Sigma is fixed, not learned: ``log_std`` is set to ``log(sigma)``, has
    ``requires_grad=False`` and is left out of the optimizer, so it keeps its value through any amount of
    training (PPO's entropy bonus is then a constant). With ``learn_sigma`` the log-std starts at ``log(sigma)`` and
    is trained like the other parameters (one value per action dimension, independent of the state, as in SB3).
    Every other argument is SB3's :class:`~stable_baselines3.common.policies.ActorCriticPolicy`'s; ``net_arch`` defaults to
    :data:`DEFAULT_NET_ARCH` (or :data:`DEFAULT_TEAM_NET_ARCH` with ``team_size``) and ``activation_fn`` to tanh.

    :param observation_space: observation space (a flat Box for the team critic)
    :param action_space: action space; must be a Box (Gaussian actions)
    :param lr_schedule: learning-rate schedule
    :param net_arch: hidden widths of actor and critic, as in SB3 (``dict(pi=[...], vf=[...])``). With
        ``team_size``, the first ``TEAM_EMBED_LAYERS`` (= 2) widths of ``vf`` are applied per agent and the
        rest after the mean over agents.
    :param activation_fn: activation of the hidden layers (the actor's output always goes through tanh)
    :param sigma: standard deviation of the Gaussian, > 0 (thesis 4.3: 0.7, fixed); the initial one with ``learn_sigma``
    :param learn_sigma: train the log-std (state-independent) instead of keeping sigma fixed
    :param action_scale: factor on the tanh of the actor's output, > 0 (thesis 4.1.2: 0.01 for the chapter-4
        individual reward scheme, 1 otherwise)
    :param team_size: ``None`` for the per-agent critic; an int n for the team critic of thesis fig. 4.3, whose
        observations are ``[own (D), team agent 0 (D), ..., team agent n-1 (D)]``, ``D = obs_dim // (1 + n)``
    :param use_sde: must be False (gSDE learns its noise)
    :param kwargs: the remaining keyword arguments of :class:`ActorCriticPolicy` (``ortho_init``,
        ``features_extractor_class``, ``optimizer_class``, ...); ``log_std_init`` is replaced by ``sigma``. Without
        ``optimizer_kwargs`` Adam gets SB3's eps of 1e-5 and torch's fused implementation (same update, faster)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: NetArch | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        sigma: float = DEFAULT_SIGMA,
        learn_sigma: bool = False,
        action_scale: float = 1.0,
        team_size: int | None = None,
        use_sde: bool = False,
        **kwargs: Any,
    ) -> None:
        check_action_distribution("FormationPolicy", action_space, sigma, action_scale, use_sde)
        if team_size is not None:
            if isinstance(team_size, bool) or not isinstance(team_size, numbers.Integral) or team_size < 1:
                raise ValueError(f"team_size must be None or an int >= 1, got {team_size!r}")
            team_size = int(team_size)
        if kwargs.get("log_std_init") is not None:
            raise ValueError("FormationPolicy takes sigma (a fixed standard deviation) instead of log_std_init")
        kwargs.pop("log_std_init", None)
        if team_size is not None and not (isinstance(observation_space, spaces.Box) and len(observation_space.shape) == 1):
            raise ValueError(f"the team critic needs a flat Box observation space, got {observation_space}")
        if net_arch is None:
            net_arch = DEFAULT_TEAM_NET_ARCH if team_size is not None else DEFAULT_NET_ARCH
            net_arch = {key: list(widths) for key, widths in net_arch.items()}
        kwargs["optimizer_kwargs"] = default_optimizer_kwargs(
            kwargs.get("optimizer_class", th.optim.Adam), kwargs.get("optimizer_kwargs")
        )
        # Read by _build, which ActorCriticPolicy.__init__ calls.
        self.sigma = float(sigma)
        self.learn_sigma = bool(learn_sigma)
        self.action_scale = float(action_scale)
        self.team_size = team_size
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,
            activation_fn=activation_fn,
            use_sde=False,
            log_std_init=math.log(self.sigma),
            **kwargs,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.pop("log_std_init", None)  # derived from sigma
        data.update(sigma=self.sigma, learn_sigma=self.learn_sigma, action_scale=self.action_scale, team_size=self.team_size)
        return data

    def _build_mlp_extractor(self) -> None:
        """SB3's :class:`MlpExtractor`, or a :class:`TeamCriticExtractor` when ``team_size`` is set."""
        if self.team_size is None:
            super()._build_mlp_extractor()
            return
        self.mlp_extractor = TeamCriticExtractor(
            self.features_dim,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            team_size=self.team_size,
            device=self.device,
        )

    def _build(self, lr_schedule: Schedule) -> None:
        """SB3's networks and orthogonal init; then, unless ``learn_sigma``, freeze ``log_std`` at log(sigma) and keep it
        out of the optimizer."""
        super()._build(lr_schedule)  # log_std = log(sigma) through log_std_init
        self.log_std.requires_grad_(self.learn_sigma)
        trainable = [param for param in self.parameters() if param.requires_grad]
        self.optimizer = self.optimizer_class(trainable, lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]

    def _mean_actions(self, latent_pi: th.Tensor) -> th.Tensor:
        """The mean of the action distribution: ``action_scale * tanh(action_net(latent_pi))``."""
        return self.action_scale * th.tanh(self.action_net(latent_pi))

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> Distribution:
        """Gaussian with mean :meth:`_mean_actions` and the (fixed or learned) ``log_std``."""
        gaussian = cast(DiagGaussianDistribution, self.action_dist)  # the action space is a Box
        return gaussian_actions(gaussian, self._mean_actions(latent_pi), self.log_std)

    def deterministic_actions(self, observations: np.ndarray) -> np.ndarray:
        """What ``predict(observations, deterministic=True)`` returns, the same numbers, without building the action
        distribution (a third of ``predict``'s time for a few hundred rows): SB3's tensor conversion, the actor, the
        distribution's mean, and the clip to the action space.

        :param observations: ``(rows, obs_dim)`` observations as the network reads them (normalised)
        """
        self.set_training_mode(False)
        tensor, _ = self.obs_to_tensor(observations)
        with th.no_grad():
            features = BasePolicy.extract_features(self, tensor, self.pi_features_extractor)
            means = self._mean_actions(self.mlp_extractor.forward_actor(features))
        box = cast(spaces.Box, self.action_space)
        actions = means.cpu().numpy().reshape((-1, *box.shape))
        return np.clip(actions, box.low, box.high)
