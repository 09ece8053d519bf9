"""Building blocks shared by the MLP and the recurrent policies: dense stacks, argument checks, the optimiser default
and the action distribution."""

from __future__ import annotations

import math
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution
from torch import nn
from torch.distributions import Normal


class ModeOnChange:
    """Mixin for SB3 policies: ``set_training_mode`` switches the modules only when the mode changes.

    SB3's ``predict`` calls ``set_training_mode(False)``, which walks every sub-module, on every call, a noticeable
    share of a policy's step in an evaluation of a few teams. The
    mode is read from the policy itself, which ``train(mode)`` sets together with its sub-modules.
    """

    training: bool  # the torch module's flag, in the policy class this is mixed into

    def set_training_mode(self, mode: bool) -> None:
        if mode != self.training:
            super().set_training_mode(mode)  # type: ignore[misc]  # SB3's BasePolicy, after this mixin in the MRO


def mlp(input_dim: int, widths: list[int], activation_fn: type[nn.Module]) -> tuple[nn.Sequential, int]:
    """Linear + activation for each width.

    :param input_dim: size of the input
    :param widths: widths of the layers, first to last (may be empty: the identity)
    :param activation_fn: activation after every layer
    :return: the stack and its output width
    """
    layers: list[nn.Module] = []
    for width in widths:
        layers += [nn.Linear(input_dim, width), activation_fn()]
        input_dim = width
    return nn.Sequential(*layers), input_dim


def check_action_distribution(
    policy: str, action_space: spaces.Space, sigma: float, action_scale: float, use_sde: bool
) -> None:
    """Raise ``ValueError`` unless the Gaussian with fixed ``sigma`` and mean ``action_scale * tanh(...)`` can be built.

    :param policy: the policy's class name, for the messages
    :param action_space: must be a Box (Gaussian actions)
    :param sigma: fixed standard deviation, a finite number > 0
    :param action_scale: factor on the tanh of the actor's output, a finite number > 0
    :param use_sde: must be False (gSDE learns its noise)
    """
    if not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a finite number > 0, got {sigma}")
    if not (math.isfinite(action_scale) and action_scale > 0):
        raise ValueError(f"action_scale must be a finite number > 0, got {action_scale}")
    if not isinstance(action_space, spaces.Box):
        raise ValueError(f"{policy} needs a Box action space (Gaussian actions), got {action_space}")
    if use_sde:
        raise ValueError(f"{policy} does not support use_sde=True: its standard deviation is fixed (sigma)")


def default_optimizer_kwargs(
    optimizer_class: type[th.optim.Optimizer], optimizer_kwargs: dict[str, Any] | None
) -> dict | None:
    """SB3's own Adam default (eps 1e-5) with torch's fused kernel (the same update, ~5x faster on CPU), unless the
    caller chose an optimiser or its arguments."""
    if optimizer_class is th.optim.Adam and optimizer_kwargs is None:
        return {"eps": 1e-5, "fused": True}
    return optimizer_kwargs


def gaussian_actions(
    distribution: DiagGaussianDistribution, mean_actions: th.Tensor, log_std: th.Tensor
) -> DiagGaussianDistribution:
    """SB3's ``DiagGaussianDistribution.proba_distribution`` (the same Gaussian, bit for bit) without torch's argument
    checks, which cost 8 % of a forward pass on 84 observations (``benchmarks/rollout_breakdown.py`` on an AMD EPYC:
    384 against 354 us). A non-finite mean then reaches the VecEnv, which refuses the action, naming the team and agent.

    :param distribution: the policy's action distribution
    :param mean_actions: ``(batch, action_dim)`` means
    :param log_std: ``(action_dim,)`` log standard deviations
    :return: ``distribution``, set to the Gaussian
    """
    distribution.distribution = Normal(mean_actions, th.ones_like(mean_actions) * log_std.exp(), validate_args=False)
    return distribution
