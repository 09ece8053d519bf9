"""Imitation pretraining of the actor on a controller's actions, with DAgger relabelling, before PPO.

Round 0 lets the teacher (a controller) fly the training env; every later round r lets the student (the actor's mean
action) fly it, except that each step is the teacher's with probability ``0.5 ** r``. Every visited state is labelled
with the teacher's action on it (DAgger, Ross et al. 2011), added to one growing data set, and after each round the
actor's mean action is fitted to the labels by mean squared error. The observations are stored raw and normalised
with the env's current statistics at every fit, so the statistics gathered during the rounds (the env is in
training mode) carry over to PPO. Afterwards :class:`FrozenActorCallback` can keep the actor still for PPO's first
iterations, while the critic learns the values of the pretrained actor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, unwrap_vec_wrapper

from sb3_formation.controllers.base import Controller
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.utils.checks import is_count, is_integer, is_number


@dataclass(frozen=True)
class ImitationSettings:
    """How the actor is pretrained (a recipe's ``imitation:`` block, apart from its teacher).

    :param rounds: data-collection rounds (round 0 flown by the teacher, later ones mostly by the student)
    :param steps: env steps per round (each gives one labelled state per slot)
    :param epochs: passes over the whole data set after each round
    :param batch_size: states per gradient step
    :param learning_rate: Adam learning rate of the fit
    :param critic_warmup: PPO iterations after pretraining during which the actor is frozen (0: none)
    """

    rounds: int = 4
    steps: int = 256
    epochs: int = 5
    batch_size: int = 2048
    learning_rate: float = 1e-3
    critic_warmup: int = 10

    def __post_init__(self) -> None:
        for name in ("rounds", "steps", "epochs", "batch_size"):
            value = getattr(self, name)
            if not (is_integer(value) and value >= 1):
                raise ValueError(f"imitation: {name} must be an integer >= 1, got {value!r}")
        if not is_count(self.critic_warmup):
            raise ValueError(f"imitation: critic_warmup must be an integer >= 0, got {self.critic_warmup!r}")
        rate = self.learning_rate
        if not (is_number(rate) and rate > 0):
            raise ValueError(f"imitation: learning_rate must be a number > 0, got {rate!r}")


def actor_parameters(policy: Any) -> list[th.nn.Parameter]:
    """The parameters that move the action distribution: the actor's layers, the action head and a learned log-std
    (a fixed sigma's is left out)."""
    parameters = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters()]
    return [*parameters, policy.log_std] if policy.log_std.requires_grad else parameters


def collect(
    model: PPO, teacher: Controller, steps: int, teacher_share: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Fly the model's training env for ``steps`` steps; return the raw observations and the teacher's actions on them.

    :param teacher_share: probability that a step is flown by the teacher (else by the student's mean action)
    """
    env = cast(VecEnv, model.get_env())  # a training env, whose normaliser is a ScaleNormalizeVecEnv
    normalizer = cast(ScaleNormalizeVecEnv, unwrap_vec_wrapper(env, ScaleNormalizeVecEnv))
    width = normalizer.agent_obs_dim
    observations = env.reset()
    raw_rows, labels = [], []
    for _ in range(steps):
        raw = normalizer.get_original_obs()
        label = teacher.predict(raw[:, :width])[0]
        raw_rows.append(raw.astype(np.float32))
        labels.append(label)
        if rng.random() < teacher_share:
            actions = label
        else:
            actions = model.policy.predict(cast(np.ndarray, observations), deterministic=True)[0]  # a Box's observations
        observations, *_ = env.step(actions)
    return np.concatenate(raw_rows), np.concatenate(labels)


def fit_actor(model: PPO, raw: np.ndarray, labels: np.ndarray, settings: ImitationSettings, rng: np.random.Generator) -> float:
    """Fit the actor's mean action to ``labels`` for ``settings.epochs`` passes; return the last epoch's mean loss."""
    policy = model.policy
    # as in collect
    normalizer = cast(ScaleNormalizeVecEnv, unwrap_vec_wrapper(cast(VecEnv, model.get_env()), ScaleNormalizeVecEnv))
    observations = th.as_tensor(normalizer.normalize_obs(raw), device=policy.device)
    targets = th.as_tensor(labels, device=policy.device)
    optimizer = th.optim.Adam(actor_parameters(policy), lr=settings.learning_rate)
    policy.set_training_mode(True)
    losses: list[float] = []
    for _ in range(settings.epochs):
        losses = []
        for batch in np.array_split(rng.permutation(len(raw)), max(1, len(raw) // settings.batch_size)):
            index = th.as_tensor(batch, device=policy.device)
            mean = policy.get_distribution(observations[index]).mode()
            loss = ((mean - targets[index]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
    policy.set_training_mode(False)
    return float(np.mean(losses))


def pretrain_actor(
    model: PPO, teacher: Controller, settings: ImitationSettings, seed: int, log: Any = None
) -> list[dict[str, float]]:
    """Behaviour cloning with DAgger relabelling (module docstring) in the model's training env.

    :param model: a PPO model with a (non-recurrent) formation policy and its training env
    :param teacher: the controller to imitate, acting in the env's task
    :param settings: rounds, steps, epochs, batch size, learning rate
    :param seed: seed of the teacher/student choice and of the batches
    :param log: called with each round's record (``round``, ``states``, ``teacher_share``, ``loss``)
    :return: one record per round
    """
    rng = np.random.default_rng(seed)
    # SB3 initialises the action head with gain 0.01 (near-zero first actions); that small head also scales down the
    # gradients reaching the hidden layers, which then barely move for hundreds of steps: start the fit from gain 1
    with th.no_grad():
        th.nn.init.orthogonal_(cast(th.Tensor, model.policy.action_net.weight), gain=1.0)  # a Linear layer's
    raw_sets, label_sets, records = [], [], []
    for round_index in range(settings.rounds):
        share = 0.5**round_index
        raw, labels = collect(model, teacher, settings.steps, share, rng)
        raw_sets.append(raw)
        label_sets.append(labels)
        loss = fit_actor(model, np.concatenate(raw_sets), np.concatenate(label_sets), settings, rng)
        record = {"round": round_index, "states": sum(len(r) for r in raw_sets), "teacher_share": share, "loss": loss}
        records.append(record)
        if log is not None:
            log(record)
    return records


class FrozenActorCallback(BaseCallback):
    """Keeps the actor's parameters still (no gradients) until the curriculum's iteration count reaches ``iterations``,
    so PPO's first updates train the critic alone on the pretrained actor's returns.

    :param iterations: iterations (counted over the whole run, resumes included) with a frozen actor
    :param curriculum: the run's curriculum callback (its ``iteration``)
    """

    def __init__(self, iterations: int, curriculum: Any) -> None:
        super().__init__()
        self.iterations, self.curriculum = iterations, curriculum
        self.trainable: list[th.nn.Parameter] = []

    def _on_training_start(self) -> None:
        self.trainable = [parameter for parameter in actor_parameters(self.model.policy) if parameter.requires_grad]

    def _on_rollout_end(self) -> None:
        # the curriculum (called first) has counted the rollout that just ended; its update follows
        frozen = self.curriculum.iteration <= self.iterations
        for parameter in self.trainable:
            parameter.requires_grad_(not frozen)

    def _on_step(self) -> bool:
        return True
