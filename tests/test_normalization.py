"""ScaleNormalizeVecEnv: running variance against numpy, scale-only output, flags, team blocks, terminal observations,
frozen statistics, save / load, and constant features."""

from __future__ import annotations

import os
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv

#: Per-agent layout of the fake env: [continuous, continuous (mean far from 0), binary flag, constant zero, continuous]
AGENT_OBS_DIM = 5
BINARY_MASK = np.array([False, False, True, False, False])
SCALES = np.array([2.0, 0.5, 1.0, 0.0, 3.0])
OFFSETS = np.array([0.0, 4.0, 0.0, 0.0, -1.0])
EPISODE_LENGTH = 4


class BlockEnv(gymnasium.Env):
    """One slot: k blocks of the per-agent layout, seeded random values, an episode ends every ``EPISODE_LENGTH`` steps."""

    def __init__(self, n_blocks: int = 1):
        self.n_blocks = n_blocks
        size = n_blocks * AGENT_OBS_DIM
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), dtype=np.float32)
        self.t = 0

    def _obs(self) -> np.ndarray:
        blocks = OFFSETS + SCALES * self.np_random.normal(size=(self.n_blocks, AGENT_OBS_DIM))
        blocks[:, 2] = self.np_random.integers(0, 2, size=self.n_blocks)
        return blocks.reshape(-1).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.t += 1
        return self._obs(), 0.0, False, self.t >= EPISODE_LENGTH, {}


def make_venv(n_blocks: int = 1, n_envs: int = 3, seed: int = 0) -> DummyVecEnv:
    venv = DummyVecEnv([lambda: BlockEnv(n_blocks) for _ in range(n_envs)])
    venv.seed(seed)
    return venv


def make_wrapper(n_blocks: int = 1, n_envs: int = 3, seed: int = 0, **kwargs) -> ScaleNormalizeVecEnv:
    return ScaleNormalizeVecEnv(make_venv(n_blocks, n_envs, seed), AGENT_OBS_DIM, BINARY_MASK, **kwargs)


def run(wrapper: ScaleNormalizeVecEnv, n_steps: int) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """Reset, then step ``n_steps`` times; return the raw and normalised observations and the infos of every call."""
    raw, normalised, infos = [], [], []
    normalised.append(wrapper.reset())
    raw.append(wrapper.get_original_obs())
    actions = np.zeros((wrapper.num_envs, 1), dtype=np.float32)
    for _ in range(n_steps):
        obs, _, _, step_infos = wrapper.step(actions)
        normalised.append(obs)
        raw.append(wrapper.get_original_obs())
        infos.append(step_infos)
    return raw, normalised, infos


def own_stream(raw: list[np.ndarray]) -> np.ndarray:
    """The first block of every slot at every reset and step, as float64 rows."""
    return np.concatenate([obs[:, :AGENT_OBS_DIM] for obs in raw]).astype(np.float64)


@pytest.mark.parametrize("n_blocks", [1, 3])
def test_running_variance_matches_numpy(n_blocks: int) -> None:
    wrapper = make_wrapper(n_blocks)
    raw, normalised, _ = run(wrapper, 40)
    stream = own_stream(raw)
    assert stream.shape == (41 * 3, AGENT_OBS_DIM)
    np.testing.assert_allclose(wrapper.obs_rms.var, np.var(stream, axis=0), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(wrapper.obs_rms.mean, np.mean(stream, axis=0), rtol=1e-6, atol=1e-12)
    assert wrapper.obs_rms.count == stream.shape[0]
    # the last output: raw / std of the whole stream, no mean subtracted (feature 1 has mean 4: subtracting would show)
    std = np.std(stream, axis=0)
    continuous = ~BINARY_MASK & (std > 0)
    last_raw = raw[-1].reshape(3, n_blocks, AGENT_OBS_DIM).astype(np.float64)
    last_out = normalised[-1].reshape(3, n_blocks, AGENT_OBS_DIM)
    np.testing.assert_allclose(last_out[..., continuous], last_raw[..., continuous] / std[continuous], rtol=1e-5)
    assert normalised[-1].dtype == np.float32
    assert normalised[-1].shape == (3, n_blocks * AGENT_OBS_DIM)


def test_output_at_every_step_uses_statistics_including_that_step() -> None:
    wrapper = make_wrapper(clip_obs=None)
    raw, normalised, _ = run(wrapper, 6)
    for index in range(1, len(raw)):
        std = np.std(own_stream(raw[: index + 1]), axis=0)
        np.testing.assert_allclose(normalised[index][:, [0, 1, 4]], raw[index][:, [0, 1, 4]] / std[[0, 1, 4]], rtol=1e-5)


@pytest.mark.parametrize("n_blocks", [1, 3])
def test_binary_features_pass_through(n_blocks: int) -> None:
    wrapper = make_wrapper(n_blocks)
    raw, normalised, _ = run(wrapper, 10)
    binary = np.tile(BINARY_MASK, n_blocks)
    for raw_obs, out in zip(raw, normalised):
        np.testing.assert_array_equal(out[:, binary], raw_obs[:, binary])
        assert set(np.unique(out[:, binary])) <= {0.0, 1.0}


def test_team_blocks_use_own_statistics_and_do_not_update_them() -> None:
    team = make_wrapper(n_blocks=3, seed=7)
    raw, normalised, _ = run(team, 20)
    # the statistics equal those of a stream made of the first blocks only
    stream = own_stream(raw)
    np.testing.assert_allclose(team.obs_rms.var, np.var(stream, axis=0), rtol=1e-6, atol=1e-12)
    # and differ from what the team blocks would have given (they come from other random draws)
    everything = np.concatenate([obs.reshape(-1, AGENT_OBS_DIM) for obs in raw]).astype(np.float64)
    assert not np.allclose(team.obs_rms.var, np.var(everything, axis=0), rtol=1e-6)
    # every block is scaled by the same own-block standard deviation
    std = np.std(stream, axis=0)
    blocks_raw = raw[-1].reshape(3, 3, AGENT_OBS_DIM).astype(np.float64)
    blocks_out = normalised[-1].reshape(3, 3, AGENT_OBS_DIM)
    cont = [0, 1, 4]
    for block in range(3):
        np.testing.assert_allclose(blocks_out[:, block, cont], blocks_raw[:, block, cont] / std[cont], rtol=1e-5)


def test_terminal_observation_normalised_with_same_statistics() -> None:
    plain = make_venv(n_blocks=3, seed=3)
    wrapper = make_wrapper(n_blocks=3, seed=3)
    plain.reset()
    wrapper.reset()
    actions = np.zeros((3, 1), dtype=np.float32)
    for _ in range(EPISODE_LENGTH):
        _, _, _, plain_infos = plain.step(actions)
        count = wrapper.obs_rms.count
        obs, _, dones, infos = wrapper.step(actions)
    assert dones.all()
    # the terminal observations did not enter the statistics: only the reset observations returned in their place
    assert wrapper.obs_rms.count == count + 3
    for index, (plain_info, info) in enumerate(zip(plain_infos, infos)):
        terminal = info["terminal_observation"]
        assert terminal.dtype == np.float32
        np.testing.assert_array_equal(terminal, wrapper.normalize_obs(plain_info["terminal_observation"]))
        assert not np.allclose(terminal, obs[index])


def test_training_false_freezes_statistics() -> None:
    wrapper = make_wrapper()
    run(wrapper, 10)
    mean, var, count = wrapper.obs_rms.mean.copy(), wrapper.obs_rms.var.copy(), wrapper.obs_rms.count
    wrapper.training = False
    raw, normalised, _ = run(wrapper, 10)
    np.testing.assert_array_equal(wrapper.obs_rms.mean, mean)
    np.testing.assert_array_equal(wrapper.obs_rms.var, var)
    assert wrapper.obs_rms.count == count
    for raw_obs, out in zip(raw, normalised):
        np.testing.assert_array_equal(out, wrapper.normalize_obs(raw_obs))


def test_normalize_obs_does_not_update() -> None:
    wrapper = make_wrapper()
    run(wrapper, 3)
    state = wrapper.state_dict()
    wrapper.normalize_obs(np.full((3, AGENT_OBS_DIM), 100.0))
    for key, value in wrapper.state_dict().items():
        np.testing.assert_array_equal(value, state[key])


def test_fresh_statistics_leave_observations_almost_unchanged() -> None:
    wrapper = make_wrapper(training=False)
    obs = wrapper.reset()
    np.testing.assert_allclose(obs, wrapper.get_original_obs(), rtol=1e-7)
    assert wrapper.obs_rms.count == 0


def test_constant_zero_feature_stays_finite() -> None:
    wrapper = make_wrapper(n_blocks=3)
    _, normalised, infos = run(wrapper, 10)
    assert wrapper.obs_rms.var[3] == 0.0
    for out in normalised:
        assert np.all(np.isfinite(out))
        np.testing.assert_array_equal(out.reshape(3, 3, AGENT_OBS_DIM)[..., 3], 0.0)
    for step_infos in infos:
        for info in step_infos:
            if "terminal_observation" in info:
                assert np.all(np.isfinite(info["terminal_observation"]))


def test_observation_space() -> None:
    wrapper = make_wrapper(n_blocks=3)
    space = wrapper.observation_space
    assert space.shape == (15,) and space.dtype == np.float32
    obs = wrapper.reset()
    assert all(space.contains(row) for row in obs)


def test_save_load_round_trip(tmp_path: Path) -> None:
    wrapper = make_wrapper(n_blocks=3)
    raw, _, _ = run(wrapper, 12)
    path = tmp_path / "vecnormalize.npz"
    wrapper.save(path)
    assert sorted(os.listdir(tmp_path)) == ["vecnormalize.npz"]
    with np.load(path) as data:
        assert set(data.files) == {"mean", "var", "count", "agent_obs_dim", "binary_mask", "epsilon", "clip_obs", "center"}
    venv = make_venv(n_blocks=3, seed=1)
    loaded = ScaleNormalizeVecEnv.load(path, venv, agent_obs_dim=AGENT_OBS_DIM, binary_mask=BINARY_MASK)
    assert loaded.training is False
    assert loaded.epsilon == wrapper.epsilon
    for raw_obs in raw:
        np.testing.assert_array_equal(loaded.normalize_obs(raw_obs), wrapper.normalize_obs(raw_obs))
    # frozen by default; training=True resumes updates
    count = loaded.obs_rms.count
    run(loaded, 3)
    assert loaded.obs_rms.count == count
    resumed = ScaleNormalizeVecEnv.load(str(path), make_venv(n_blocks=3), training=True)
    run(resumed, 3)
    assert resumed.obs_rms.count == count + 4 * 3


def test_statistics_transfer_between_block_counts(tmp_path: Path) -> None:
    team = make_wrapper(n_blocks=3)
    raw, _, _ = run(team, 5)
    team.save(tmp_path / "stats.npz")
    single = ScaleNormalizeVecEnv.load(tmp_path / "stats.npz", make_venv(n_blocks=1))
    own = raw[-1][:, :AGENT_OBS_DIM]
    np.testing.assert_array_equal(single.normalize_obs(own), team.normalize_obs(raw[-1])[:, :AGENT_OBS_DIM])


def test_state_dict_round_trip() -> None:
    wrapper = make_wrapper()
    raw, _, _ = run(wrapper, 8)
    state = wrapper.state_dict()
    assert all(isinstance(value, np.ndarray) for value in state.values())
    other = make_wrapper(seed=5)
    other.load_state_dict(state)
    np.testing.assert_array_equal(other.normalize_obs(raw[-1]), wrapper.normalize_obs(raw[-1]))
    # a copy: updating the wrapper does not change the dict
    run(wrapper, 2)
    assert state["count"] != wrapper.obs_rms.count


def test_save_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "stats.npz"
    old = make_wrapper(seed=1)
    run(old, 3)
    old.save(path)
    old_bytes = path.read_bytes()

    new = make_wrapper(seed=2)
    run(new, 9)

    def failing_savez(file, *args, **kwargs) -> None:
        file.write(b"partial data that is not an npz file")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError, match="disk full"):
        new.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == old_bytes
    assert sorted(os.listdir(tmp_path)) == ["stats.npz"]
    reloaded = ScaleNormalizeVecEnv.load(path, make_venv())
    np.testing.assert_array_equal(reloaded.obs_rms.var, old.obs_rms.var)


def test_load_rejects_mismatched_agent_obs_dim(tmp_path: Path) -> None:
    path = tmp_path / "stats.npz"
    make_wrapper().save(path)
    with pytest.raises(ValueError, match=r"observation size 5 is not a multiple of agent_obs_dim 6"):
        ScaleNormalizeVecEnv.load(path, make_venv(), agent_obs_dim=6)
    with pytest.raises(ValueError, match=r"stats.npz.*agent_obs_dim 5 but this environment has agent_obs_dim 10"):
        ScaleNormalizeVecEnv.load(path, make_venv(n_blocks=2), agent_obs_dim=10, binary_mask=np.zeros(10, dtype=bool))
    # an environment whose observation size is not a multiple of the saved agent_obs_dim
    other = DummyVecEnv([lambda: gymnasium.make("CartPole-v1")])
    with pytest.raises(ValueError, match=r"observation size 4 is not a multiple of agent_obs_dim 5"):
        ScaleNormalizeVecEnv.load(path, other)


def test_load_rejects_mismatched_mask(tmp_path: Path) -> None:
    path = tmp_path / "stats.npz"
    make_wrapper().save(path)
    wrong = BINARY_MASK.copy()
    wrong[0] = True
    with pytest.raises(ValueError, match=r"1 of 5 binary.*2 of 5 binary.*features \[0\]"):
        ScaleNormalizeVecEnv.load(path, make_venv(), binary_mask=wrong)
    with pytest.raises(ValueError, match=r"shape \(6,\) but agent_obs_dim is 5"):
        ScaleNormalizeVecEnv.load(path, make_venv(), binary_mask=np.zeros(6, dtype=bool))


def test_load_state_dict_rejects_mismatches() -> None:
    state = make_wrapper().state_dict()
    with pytest.raises(ValueError, match=r"agent_obs_dim 5.*agent_obs_dim 10"):
        ScaleNormalizeVecEnv(make_venv(n_blocks=2), 10, np.zeros(10, dtype=bool)).load_state_dict(state)
    wrong = BINARY_MASK.copy()
    wrong[4] = True
    with pytest.raises(ValueError, match=r"1 of 5 binary.*2 of 5 binary.*\[4\]"):
        ScaleNormalizeVecEnv(make_venv(), AGENT_OBS_DIM, wrong).load_state_dict(state)
    del state["var"]
    with pytest.raises(ValueError, match="var"):
        make_wrapper().load_state_dict(state)


def test_load_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "stats.npz"
    with pytest.raises(FileNotFoundError, match=r"nowhere/stats\.npz"):
        ScaleNormalizeVecEnv.load(path, make_venv())


@pytest.mark.parametrize(
    ("agent_obs_dim", "mask", "message"),
    [
        (4, np.zeros(4, dtype=bool), r"observation size 5 is not a multiple of agent_obs_dim 4"),
        (5, np.zeros(4, dtype=bool), r"binary_mask has shape \(4,\) but agent_obs_dim is 5"),
        (5, np.zeros(5), r"bool array"),
        (0, np.zeros(0, dtype=bool), r"positive integer"),
    ],
)
def test_constructor_validates(agent_obs_dim: int, mask: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ScaleNormalizeVecEnv(make_venv(), agent_obs_dim, mask)


def test_constructor_validates_epsilon() -> None:
    with pytest.raises(ValueError, match="epsilon"):
        ScaleNormalizeVecEnv(make_venv(), AGENT_OBS_DIM, BINARY_MASK, epsilon=0.0)


def test_get_original_obs_before_reset() -> None:
    with pytest.raises(RuntimeError, match="reset"):
        make_wrapper().get_original_obs()


def test_observation_space_bounds_keep_signs_and_flags() -> None:
    class BoundedEnv(BlockEnv):
        def __init__(self) -> None:
            super().__init__(n_blocks=2)
            low = np.tile(np.array([0.0, -1.0, 0.0, 0.0, -3.0], dtype=np.float32), 2)
            high = np.tile(np.array([1.0, 0.0, 1.0, 0.0, 3.0], dtype=np.float32), 2)
            self.observation_space = gymnasium.spaces.Box(low, high, dtype=np.float32)

    for clip_obs, bound in ((None, np.inf), (10.0, 10.0)):
        wrapper = ScaleNormalizeVecEnv(DummyVecEnv([BoundedEnv]), AGENT_OBS_DIM, BINARY_MASK, clip_obs=clip_obs)
        np.testing.assert_array_equal(wrapper.observation_space.low, np.tile([0.0, -bound, 0.0, 0.0, -bound], 2))
        np.testing.assert_array_equal(wrapper.observation_space.high, np.tile([bound, 0.0, 1.0, 0.0, bound], 2))


def test_scaled_values_are_clipped_but_flags_untouched() -> None:
    """A feature constant so far (variance 0) would be scaled by 1 / sqrt(1e-8) = 1e4: the clip bounds it at 10."""
    wrapper = make_wrapper()
    wrapper.obs_rms.var[:] = 0.0
    observation = np.tile(np.array([1.0, -0.5, 1.0, 0.0, 1e-5], dtype=np.float32), (1, 1))
    normalised = wrapper.normalize_obs(observation)
    # features 0, 1, 4 scale: 1 -> 1e4 -> 10; -0.5 -> -5e3 -> -10; 1e-5 -> 0.1 (kept); binary features 2 and 3 unchanged
    expected = np.where(BINARY_MASK, observation, np.clip(observation / np.sqrt(1e-8), -10, 10))
    np.testing.assert_allclose(normalised, expected, rtol=1e-6)
    assert wrapper.state_dict()["clip_obs"] == 10.0
    unclipped = make_wrapper(clip_obs=None)
    unclipped.load_state_dict(wrapper.state_dict())
    assert unclipped.clip_obs == 10.0


def test_centred_output_subtracts_the_running_mean_from_continuous_features(tmp_path: Path) -> None:
    wrapper = make_wrapper(center=True, clip_obs=None)
    raw, normalised, _ = run(wrapper, 6)
    stream = own_stream(raw)
    expected = (raw[-1] - stream.mean(axis=0)) / np.sqrt(stream.var(axis=0) + wrapper.epsilon)
    expected[:, 2] = raw[-1][:, 2]  # the flag is left alone
    np.testing.assert_allclose(normalised[-1], expected, rtol=1e-5, atol=1e-6)
    space = wrapper.observation_space  # centred features fall on both sides of 0; the flag keeps its bounds
    assert space.low[1] == -np.inf and space.high[1] == np.inf and (space.low[2], space.high[2]) == (-np.inf, np.inf)
    wrapper.save(tmp_path / "centred.npz")
    loaded = ScaleNormalizeVecEnv.load(tmp_path / "centred.npz", make_venv())
    assert loaded.center and loaded.observation_space.low[0] < 0 < loaded.observation_space.high[0]
    np.testing.assert_array_equal(loaded.normalize_obs(raw[-1]), wrapper.normalize_obs(raw[-1]))
    with pytest.raises(ValueError, match="saved statistics have center=True but this wrapper has center=False"):
        make_wrapper().load_state_dict(wrapper.state_dict())


def test_files_saved_before_centring_existed_load_as_scale_only(tmp_path: Path) -> None:
    wrapper = make_wrapper()
    raw, _, _ = run(wrapper, 4)
    state = {key: value for key, value in wrapper.state_dict().items() if key != "center"}
    np.savez(tmp_path / "old.npz", **state)
    loaded = ScaleNormalizeVecEnv.load(tmp_path / "old.npz", make_venv())
    assert not loaded.center
    np.testing.assert_array_equal(loaded.normalize_obs(raw[-1]), wrapper.normalize_obs(raw[-1]))
