""":class:`RecurrentFormationPPO`: SB3's ``PPO`` whose rollouts carry hidden states and whose update replays sequences."""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from sb3_formation.env.geometry import ring_rows
from sb3_formation.sb3.recurrent.buffers import RecurrentRolloutBuffer
from sb3_formation.sb3.recurrent.policies import DEFAULT_MAX_SEQUENCE_LENGTH, RecurrentFormationPolicy


def _masked_mean(values: th.Tensor, mask: th.Tensor) -> th.Tensor:
    return values[mask].mean()


class RecurrentFormationPPO(PPO):
    """SB3's ``PPO`` for :class:`RecurrentFormationPolicy`: rollouts carry hidden states, updates replay sequences.

    Construction, ``learn``, callbacks, logging, ``save`` and ``load`` are SB3's. Differences from ``PPO``:

    - Each slot's actor and critic states are carried from step to step and reset when the slot's episode starts;
      time-outs are bootstrapped with the critic's state after the last real step.
    - A policy with messages (``message_size`` > 0) needs the package's
      :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` (possibly wrapped): the slots' teams tell each slot's ring
      neighbours, whose messages it receives one step late; its minibatches hold whole teams' sequences.
    - The update cuts every slot's rollout into sequences at episode starts and every ``max_sequence_length`` steps,
      and forms minibatches of about ``batch_size`` steps of whole sequences; each sequence is replayed from the
      states stored for its first step during the rollout (zeros at an episode start); losses are means over the real
      (unpadded) steps; advantages are normalised per minibatch over those steps.

    :param policy: :class:`RecurrentFormationPolicy` (the default)
    :param env: the environment
    :param max_sequence_length: longest sequence replayed in an update (``None``: up to the rollout's length)
    :param kwargs: SB3 ``PPO`` arguments
    """

    # SB3's OnPolicyAlgorithm declares an ActorCriticPolicy; this algorithm's policy is a BasePolicy of its own
    policy: RecurrentFormationPolicy  # type: ignore[assignment]
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
        super().__init__(policy, env, **kwargs)  # type: ignore[arg-type]  # a BasePolicy, not an ActorCriticPolicy (above)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.rollout_buffer.max_sequence_length = self.max_sequence_length
        self._last_states = self.policy.initial_state(self.n_envs)
        self._last_episode_starts = np.ones(self.n_envs, dtype=bool)  # zero states: a loaded model starts afresh
        self._neighbours: th.Tensor | None = None
        self._set_neighbours()

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        """SB3's ``set_env``; for a policy with messages also the slots' ring neighbours (from the env's teams)."""
        super().set_env(env, force_reset)
        self._set_neighbours()

    def _set_neighbours(self) -> None:
        """A policy with messages: each slot's ring neighbours' slots, from the env's teams (the buffer's too).

        :raises ValueError: an env that is not the package's FormationVecEnv
        """
        if not self.policy.message_size or self.env is None:
            return
        sizes = [config.n_agents for config in getattr(self.env.unwrapped, "team_configs", [])]
        if sum(sizes) != self.n_envs:
            raise ValueError("a policy with messages trains on the package's FormationVecEnv, whose slots are teams' agents")
        self.rollout_buffer.team_sizes = sizes
        self._neighbours = th.as_tensor(ring_rows(sizes), device=self.device)

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
                entering = self.policy.entering(self._last_states, starts)  # reset where an episode starts
                actions, values, log_probs, self._last_states = self.policy(
                    obs_tensor, entering, starts, False, self._neighbours
                )
            actions = actions.cpu().numpy()
            box = cast(spaces.Box, self.action_space)  # the formation env's actions
            clipped_actions = np.clip(actions, box.low, box.high)
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
            # bootstrap from the critic's state after the last real step (as SB3 does: DLR-RM/stable-baselines3 issue 633)
            if timeouts:
                terminal = obs_as_tensor(np.stack([infos[index]["terminal_observation"] for index in timeouts]), self.device)
                rows = th.as_tensor(timeouts, device=self.device)
                with th.no_grad():
                    received = self.policy.received(self._last_states.messages, self._neighbours)
                    terminal_values = self.policy.predict_values(
                        cast(th.Tensor, terminal),
                        self._last_states.select(rows).vf,
                        th.zeros(len(timeouts), device=self.device),
                        None if received is None else received[rows],
                    )
                rewards[timeouts] += self.gamma * terminal_values.squeeze(-1).cpu().numpy()
            rollout_buffer.add_states(entering)
            observed = cast(np.ndarray, self._last_obs)  # Box observations
            started = cast(np.ndarray, self._last_episode_starts)  # set in _setup_model
            rollout_buffer.add(observed, actions, rewards, started, values, log_probs)
            self._last_obs = cast(np.ndarray, new_obs)
            self._last_episode_starts = dones
        with th.no_grad():
            starts = th.as_tensor(dones, dtype=th.float32, device=self.device)
            last_obs = cast(th.Tensor, obs_as_tensor(cast(np.ndarray, new_obs), self.device))  # Box observations
            received = self.policy.received(self.policy.entering(self._last_states, starts).messages, self._neighbours)
            values = self.policy.predict_values(last_obs, self._last_states.vf, starts, received)
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """PPO's clipped update over minibatches of whole sequences (see the class docstring)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        # SB3 declares float | Schedule; _setup_model made them schedules
        clip_range = cast(Schedule, self.clip_range)(self._current_progress_remaining)
        clip_range_vf = (
            None if self.clip_range_vf is None else cast(Schedule, self.clip_range_vf)(self._current_progress_remaining)
        )
        entropy_losses, pg_losses, value_losses, clip_fractions = [], [], [], []
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for batch in self.rollout_buffer.sequence_batches(self.batch_size):
                mask = batch.mask
                values, log_prob, entropy = self.policy.evaluate_sequences(
                    batch.observations, batch.actions, batch.states, batch.neighbours
                )
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
