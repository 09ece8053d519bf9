"""Scale-only observation normalisation (thesis 3.1.4; ``docs/design.md`` "Normalisation").

Continuous observation values are divided by a running standard deviation per feature, without subtracting the mean
(tuned recipes may subtract it: ``center``), then clipped to [-10, 10] (``clip_obs``); the 0/1 flags are left as they
are. The running variance is kept with Stable-Baselines3's ``RunningMeanStd`` (Chan, Golub & LeVeque's parallel
update, the batch form of Welford's algorithm).

Every slot of the wrapped ``VecEnv`` is one agent. Its observation is one or more blocks with the same per-agent layout:
normally just the agent's own observation (k = 1); with a team critic, its own observation followed by those of the
team's n agents (k = 1 + n). The statistics hold one variance per per-agent feature and are updated from the first
block only (each agent's own observation, counted once per step); every block is scaled with them. They therefore do
not depend on k: statistics learnt with a team critic also apply to an environment without one, and vice versa.
"""

from __future__ import annotations

import os
from copy import deepcopy
from pathlib import Path
from typing import Any, cast

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvStepReturn, VecEnvWrapper

from sb3_formation.utils.files import atomic_path, read_arrays

#: Keys of ``ScaleNormalizeVecEnv.state_dict()``, which are also the arrays of the saved ``.npz`` file (files saved before
#: ``center`` existed lack it and are scale-only).
STATE_KEYS = ("mean", "var", "count", "agent_obs_dim", "binary_mask", "epsilon", "clip_obs")


class ScaleNormalizeVecEnv(VecNormalize):
    """
    Scale-only observation normalisation for a vectorized environment whose slots are agents.

    A :class:`~stable_baselines3.common.vec_env.VecNormalize` for SB3's tools: ``sync_envs_normalization`` (and so
    ``EvalCallback``) copies its ``obs_rms`` to an evaluation env's, ``model.get_vec_normalize_env()`` finds it, and
    ``ScaleNormalizeVecEnv.load(path, venv)`` loads it as ``VecNormalize.load`` does (from its own ``.npz`` file). It
    normalises observations only (``norm_reward`` is False; SB3's own ``VecNormalize`` on top divides rewards).

    Non-binary features are divided by ``sqrt(var + epsilon)``, ``var`` being the running variance of that feature over
    every agent's own observation seen so far (on reset and on every step, while ``training``). Unless ``center``,
    there is no mean subtraction; the scaled values are clipped to ``[-clip_obs, clip_obs]`` (as RLlib's ``MeanStdFilter``, the
    thesis's tool, and SB3's ``VecNormalize`` do by default, 10), which bounds the features that were (nearly)
    constant so far, such as lidar rays that have only ever read 1; ``clip_obs=None`` switches clipping off.
    Binary features pass through unchanged; observations are returned as float32.
    ``infos[i]["terminal_observation"]`` is normalised with the same statistics, without updating them.

    The statistics start empty (count 0, so after any data they are exactly those of the observations seen, with no
    prior); until the first update the variance is 1 and observations come out (almost) unchanged. A feature that has
    always been 0 stays 0; a feature that has been constant but non-zero is divided by ``sqrt(epsilon)``.

    The observation space becomes [-clip_obs, clip_obs] (unbounded without clipping) on the side(s) where the wrapped
    space allows non-zero values (scaling by a positive factor keeps signs); binary features keep their bounds.

    :param venv: the vectorized environment to wrap; its observation space must be a 1-D ``Box`` of size
        ``k * agent_obs_dim`` with k >= 1
    :param agent_obs_dim: size of one agent's observation (one block)
    :param binary_mask: bool array of length ``agent_obs_dim``, True for the 0/1 flag features that are left untouched
        (e.g. ``FormationEnv.binary_observation_mask``)
    :param training: whether to update the statistics (set to False to freeze them, e.g. for evaluation)
    :param epsilon: added to the variance before the square root, so that a constant feature gives no division by zero
    :param clip_obs: bound of the scaled non-binary features, or ``None`` for no clipping
    :param center: also subtract the running mean from the non-binary features, as SB3's ``VecNormalize`` does (a
        departure from thesis 3.1.4 for tuned recipes: without it, lidar rays that mostly read 1 come out at the clip
        bound, which slows supervised fitting of the actor)
    """

    # Observations are arrays here, never the dicts of observations SB3's VecNormalize also accepts; clip_obs may be
    # None (no clipping), which VecNormalize does not offer.
    obs_rms: RunningMeanStd  # type: ignore[assignment]
    old_obs: np.ndarray | None  # type: ignore[assignment]
    clip_obs: float | None  # type: ignore[assignment]

    def __init__(
        self,
        venv: VecEnv,
        agent_obs_dim: int,
        binary_mask: np.ndarray,
        training: bool = True,
        epsilon: float = 1e-8,
        clip_obs: float | None = 10.0,
        center: bool = False,
    ):
        observation_space = venv.observation_space
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(
                f"ScaleNormalizeVecEnv needs a 1-D gymnasium.spaces.Box observation space, not {observation_space}"
            )
        if isinstance(agent_obs_dim, bool) or not isinstance(agent_obs_dim, (int, np.integer)) or agent_obs_dim < 1:
            raise ValueError(f"agent_obs_dim must be a positive integer, got {agent_obs_dim!r}")
        agent_obs_dim = int(agent_obs_dim)
        obs_size = observation_space.shape[0]
        if obs_size % agent_obs_dim != 0:
            raise ValueError(
                f"the environment's observation size {obs_size} is not a multiple of agent_obs_dim {agent_obs_dim}: "
                "each slot's observation must be k >= 1 blocks of agent_obs_dim values"
            )
        binary_mask = np.asarray(binary_mask)
        if binary_mask.dtype != np.bool_:
            raise ValueError(f"binary_mask must be a bool array, got dtype {binary_mask.dtype}")
        if binary_mask.shape != (agent_obs_dim,):
            raise ValueError(f"binary_mask has shape {binary_mask.shape} but agent_obs_dim is {agent_obs_dim}")
        if not np.isfinite(epsilon) or epsilon <= 0:
            raise ValueError(f"epsilon must be a finite positive number, got {epsilon!r}")
        if clip_obs is not None and not (np.isfinite(clip_obs) and clip_obs > 0):
            raise ValueError(f"clip_obs must be None or a finite positive number, got {clip_obs!r}")

        self.agent_obs_dim = agent_obs_dim
        self.n_blocks = obs_size // agent_obs_dim
        self.binary_mask = binary_mask.copy()
        self.epsilon = float(epsilon)
        self.clip_obs = None if clip_obs is None else float(clip_obs)
        self.center = bool(center)
        self.training = training
        self.obs_rms = RunningMeanStd(epsilon=0.0, shape=(agent_obs_dim,))
        self.old_obs = None
        # not VecNormalize.__init__, which keeps one statistic per value of the whole observation
        VecEnvWrapper.__init__(self, venv, observation_space=self._scaled_space(observation_space))
        # VecNormalize's own attributes, as SB3's tools read them: observations only, no reward normalisation
        self.norm_obs, self.norm_reward, self.norm_obs_keys = True, False, None
        self.ret_rms = RunningMeanStd(shape=())
        self.clip_reward, self.gamma = np.inf, 0.99
        self.returns = np.zeros(self.num_envs)
        self.old_reward = np.array([])

    def _scaled_space(self, space: spaces.Box) -> spaces.Box:
        """The wrapped space after scaling: unbounded where values can be non-zero, flags keep their bounds."""
        binary = np.tile(self.binary_mask, self.n_blocks)
        bound = np.inf if self.clip_obs is None else self.clip_obs
        low = np.where(space.low < 0, -bound, 0.0)
        high = np.where(space.high > 0, bound, 0.0)
        if self.center:  # a centred feature falls on either side of 0 unless it is always 0
            low = np.where((space.low < 0) | (space.high > 0), -bound, 0.0)
            high = -low
        low[binary] = space.low[binary]
        high[binary] = space.high[binary]
        return spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)

    def _update(self, obs: np.ndarray) -> None:
        """Add the own-observation block of every slot to the statistics."""
        own = np.asarray(obs, dtype=np.float64).reshape(-1, self.n_blocks * self.agent_obs_dim)[:, : self.agent_obs_dim]
        if own.shape[0] > 0:
            self.obs_rms.update(own)

    def normalize_obs(self, obs: np.ndarray) -> np.ndarray:  # type: ignore[override]  # arrays only, as above
        """
        Normalise observations with the current statistics, without updating them.

        :param obs: one observation (shape ``(k * agent_obs_dim,)``) or a batch of them (``(..., k * agent_obs_dim)``)
        :return: a float32 copy, non-binary features divided by ``sqrt(var + epsilon)`` and clipped to ``clip_obs``
        """
        obs = np.asarray(obs)
        size = self.n_blocks * self.agent_obs_dim
        if obs.ndim == 0 or obs.shape[-1] != size:
            raise ValueError(f"observation of shape {obs.shape} does not end in the expected size {size}")
        state = {"mean": self.obs_rms.mean, "var": self.obs_rms.var, "epsilon": self.epsilon}
        state |= {"binary_mask": self.binary_mask, "center": self.center}
        return scale_observations(obs, observation_scale(state), self.clip_obs, observation_offset(state))

    def unnormalize_obs(self, obs: np.ndarray) -> np.ndarray:  # type: ignore[override]  # arrays only, as above
        """
        Undo :meth:`normalize_obs` (up to clipping) with the current statistics.

        :param obs: normalised observations of shape ``(..., k * agent_obs_dim)``
        :return: float64 raw observations
        """
        state = {"mean": self.obs_rms.mean, "var": self.obs_rms.var, "epsilon": self.epsilon}
        state |= {"binary_mask": self.binary_mask, "center": self.center}
        blocks = np.asarray(obs, dtype=np.float64).reshape(*np.shape(obs)[:-1], self.n_blocks, self.agent_obs_dim)
        offset = observation_offset(state)
        raw = blocks * observation_scale(state) + (0.0 if offset is None else offset)
        return raw.reshape(np.shape(obs))

    def get_original_obs(self) -> np.ndarray:
        """
        :return: a copy of the raw (unnormalised) observations of the most recent step or reset
        """
        if self.old_obs is None:
            raise RuntimeError("no observation yet: call reset() first")
        return deepcopy(self.old_obs)

    def reset(self) -> np.ndarray:
        """
        Reset all environments (and, while training, add their first observations to the statistics).

        :return: the normalised first observations
        """
        obs = self.venv.reset()
        assert isinstance(obs, np.ndarray)
        self.old_obs = obs
        if self.training:
            self._update(obs)
        return self.normalize_obs(obs)

    def step_wait(self) -> VecEnvStepReturn:
        """
        Step the wrapped environments; while training, add the new observations to the statistics first.

        :return: normalised observations, rewards, dones and infos (``terminal_observation`` normalised too)
        """
        obs, rewards, dones, infos = self.venv.step_wait()
        assert isinstance(obs, np.ndarray)
        self.old_obs, self.old_reward = obs, rewards
        if self.training:
            self._update(obs)
        for idx, done in enumerate(dones):
            if done and "terminal_observation" in infos[idx]:
                infos[idx]["terminal_observation"] = self.normalize_obs(infos[idx]["terminal_observation"])
        return self.normalize_obs(obs), rewards, dones, infos

    def state_dict(self) -> dict[str, np.ndarray]:
        """
        The statistics and settings as plain numpy arrays (copies), e.g. to store them beside a model.

        :return: ``mean``, ``var`` (float64, shape ``(agent_obs_dim,)``), ``count``, ``epsilon`` (0-d float64),
            ``agent_obs_dim`` (0-d int64) and ``binary_mask`` (bool, shape ``(agent_obs_dim,)``)
        """
        return {
            "mean": np.array(self.obs_rms.mean, dtype=np.float64),
            "var": np.array(self.obs_rms.var, dtype=np.float64),
            "count": np.array(self.obs_rms.count, dtype=np.float64),
            "agent_obs_dim": np.array(self.agent_obs_dim, dtype=np.int64),
            "binary_mask": self.binary_mask.copy(),
            "epsilon": np.array(self.epsilon, dtype=np.float64),
            "clip_obs": np.array(np.nan if self.clip_obs is None else self.clip_obs, dtype=np.float64),  # NaN: no clip
            "center": np.array(self.center),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        Restore statistics and ``epsilon`` from ``state_dict()``; ``training`` is left as it is.

        :param state: a mapping with the keys of ``state_dict()``
        :raises ValueError: a key is missing, or ``agent_obs_dim`` / ``binary_mask`` / the statistics do not match this
            wrapper (the message names both sizes)
        """
        missing = [key for key in STATE_KEYS if key not in state]
        if missing:
            raise ValueError(f"normalisation state lacks {missing}; expected the keys {list(STATE_KEYS)}")
        agent_obs_dim = int(np.asarray(state["agent_obs_dim"]))
        if agent_obs_dim != self.agent_obs_dim:
            raise ValueError(
                f"saved statistics are for agent_obs_dim {agent_obs_dim} but this environment has agent_obs_dim "
                f"{self.agent_obs_dim}"
            )
        binary_mask = np.asarray(state["binary_mask"])
        if binary_mask.shape != self.binary_mask.shape:
            raise ValueError(
                f"saved binary_mask has shape {binary_mask.shape} but this environment's has shape {self.binary_mask.shape}"
            )
        if binary_mask.dtype != np.bool_ or not np.array_equal(binary_mask, self.binary_mask):
            differ = np.flatnonzero(binary_mask.astype(bool) != self.binary_mask).tolist()
            raise ValueError(
                f"saved binary_mask ({int(binary_mask.astype(bool).sum())} of {binary_mask.size} binary) does not match "
                f"this environment's ({int(self.binary_mask.sum())} of {self.binary_mask.size} binary); "
                f"they differ at features {differ}"
            )
        mean = np.asarray(state["mean"], dtype=np.float64)
        var = np.asarray(state["var"], dtype=np.float64)
        for name, array in (("mean", mean), ("var", var)):
            if array.shape != (self.agent_obs_dim,):
                raise ValueError(f"saved {name} has shape {array.shape} but agent_obs_dim is {self.agent_obs_dim}")
        center = bool(np.asarray(state.get("center", False)))
        if center != self.center:
            raise ValueError(f"saved statistics have center={center} but this wrapper has center={self.center}")
        count = float(np.asarray(state["count"]))
        epsilon = float(np.asarray(state["epsilon"]))
        if not np.isfinite(count) or count < 0 or np.any(~np.isfinite(var)) or np.any(var < 0):
            raise ValueError(f"saved statistics are invalid: count {count}, var min {var.min() if var.size else None}")
        if not np.isfinite(epsilon) or epsilon <= 0:
            raise ValueError(f"saved epsilon must be a finite positive number, got {epsilon}")
        self.obs_rms.mean = mean.copy()
        self.obs_rms.var = var.copy()
        self.obs_rms.count = count
        self.epsilon = epsilon
        clip_obs = float(np.asarray(state["clip_obs"]))
        self.clip_obs = None if np.isnan(clip_obs) else clip_obs

    def save(self, save_path: str | os.PathLike[str]) -> None:
        """
        Save the statistics and settings to an ``.npz`` file (the arrays of ``state_dict()``), atomically: the data
        goes to a temporary file in the same folder, which then replaces ``save_path``. If writing fails, an existing
        file at ``save_path`` is left intact and no temporary file remains. The file is written at exactly
        ``save_path`` (no ``.npz`` suffix is appended).

        :param save_path: the path to save to; its folder must exist
        """
        with atomic_path(save_path) as temporary, open(temporary, "wb") as stream:
            np.savez(stream, **cast("dict[str, Any]", self.state_dict()))  # numpy's stubs read the keys as options

    @staticmethod
    def load(
        load_path: str | os.PathLike[str],
        venv: VecEnv,
        training: bool = False,
        agent_obs_dim: int | None = None,
        binary_mask: np.ndarray | None = None,
    ) -> ScaleNormalizeVecEnv:
        """
        Wrap ``venv`` with statistics saved by ``save()``.

        ``agent_obs_dim``, ``binary_mask`` and ``epsilon`` come from the file. Pass the environment's own
        ``agent_obs_dim`` / ``binary_mask`` to have them checked against the file (recommended: the file alone can only be
        checked against the observation size).

        :param load_path: the path to load from
        :param venv: the VecEnv to wrap
        :param training: whether the loaded statistics keep being updated; False by default (loading is mostly for
            evaluation or deployment; pass True to resume training)
        :param agent_obs_dim: the environment's per-agent observation size, if known
        :param binary_mask: the environment's binary mask, if known
        :return: the wrapped environment
        :raises FileNotFoundError: no file at ``load_path``
        :raises ValueError: the saved ``agent_obs_dim`` / ``binary_mask`` do not match the environment (both sizes named)
        """
        path = Path(load_path)
        if not path.is_file():
            raise FileNotFoundError(f"no saved normalisation statistics at {str(path)!r}")
        state = read_arrays(path, "a ScaleNormalizeVecEnv file", STATE_KEYS)
        wrapper = ScaleNormalizeVecEnv(
            venv,
            int(state["agent_obs_dim"]) if agent_obs_dim is None else agent_obs_dim,
            np.asarray(state["binary_mask"]) if binary_mask is None else np.asarray(binary_mask),
            training=training,
            center=bool(np.asarray(state.get("center", False))),
        )
        try:
            wrapper.load_state_dict(state)  # checks sizes, mask and statistics against the env's
        except ValueError as error:
            raise ValueError(f"{str(path)!r}: {error}") from error
        return wrapper


def observation_scale(state: dict[str, Any]) -> np.ndarray:
    """The divisor of each per-agent feature under the statistics ``state`` (:meth:`ScaleNormalizeVecEnv.state_dict`).

    :return: ``sqrt(var + epsilon)``, exactly 1 for the binary features (so they pass through bit-identical)
    """
    scale = np.sqrt(np.asarray(state["var"], dtype=np.float64) + float(state["epsilon"]))
    scale[np.asarray(state["binary_mask"], dtype=bool)] = 1.0
    return scale


def observation_offset(state: dict[str, Any]) -> np.ndarray | None:
    """What is subtracted from each per-agent feature before scaling: the running mean with ``center`` (0 for the
    binary features), else nothing (``None``).
    """
    if not bool(np.asarray(state.get("center", False))):
        return None
    return np.where(np.asarray(state["binary_mask"], dtype=bool), 0.0, np.asarray(state["mean"], dtype=np.float64))


def scale_observations(
    obs: np.ndarray, scale: np.ndarray, clip_obs: float | None, offset: np.ndarray | None = None
) -> np.ndarray:
    """Subtract ``offset`` from every ``scale.size``-long block of ``obs``, divide by ``scale`` and clip to
    ``[-clip_obs, clip_obs]``.

    :param obs: observations of shape ``(..., k * scale.size)``
    :param scale: per-feature divisors (:func:`observation_scale`)
    :param clip_obs: bound of the scaled values, ``None`` for none (flags are 0/1, so clipping leaves them alone)
    :param offset: per-feature offsets (:func:`observation_offset`), ``None`` for none
    :return: float32 array of the shape of ``obs``
    """
    blocks = obs.reshape((*obs.shape[:-1], -1, scale.size)).astype(np.float64)
    if offset is not None:
        blocks = blocks - offset
    blocks = blocks / scale
    if clip_obs is not None:
        blocks = np.clip(blocks, -clip_obs, clip_obs)
    return blocks.reshape(obs.shape).astype(np.float32)
