"""Videos: captions and their overlay, the MP4 and GIF writers, and render_episodes() on tiny scripted episodes."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from sb3_formation import make_formation_vec_env
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.state import TeamState
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.viz.video import (
    VideoWriter,
    episode_caption,
    frames_per_episode,
    overlay_text,
    render_episodes,
    write_video,
)

MAX_STEPS = 6


class Still:
    """A stand-in for ``PPO`` whose agents never push: every episode runs to its time-out. Counts its calls."""

    def __init__(self, fail_on_call: int | None = None) -> None:
        self.calls = 0
        self.fail_on_call = fail_on_call

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        self.calls += 1
        if self.calls == self.fail_on_call:
            raise RuntimeError(f"scripted failure on call {self.calls}")
        return np.zeros((len(observation), 2), dtype=np.float32), None


@pytest.fixture(scope="module")
def normalised() -> Iterator[SimpleNamespace]:
    """The configuration and normaliser statistics of a fresh ch5-bearing env."""
    env = make_formation_vec_env("ch5-bearing", n_envs=1, seed=0)
    yield SimpleNamespace(config=env.venv.config, state=env.state_dict())
    env.close()


def still_model(normalised: SimpleNamespace, fail_on_call: int | None = None) -> TrainedPolicy:
    return TrainedPolicy(Still(fail_on_call), normalised.config, normalised.state)


def expected_frames(config: Any, episodes: int, seed: int, frame_every: int = 1) -> list[np.ndarray]:
    """The captioned frames render_episodes should write for a policy that never pushes, replayed here by hand."""
    env = FormationEnv(config, render_mode="rgb_array")
    frames = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        frames.append(overlay_text(env.render(), episode_caption(episode, env.team_state(), config)))
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step_array(np.zeros((config.n_agents, 2)))
            done = terminated or truncated
            if env.step_count % frame_every == 0 or done:
                frames.append(overlay_text(env.render(), episode_caption(episode, env.team_state(), config)))
    return frames


def read_mp4(path: Path) -> tuple[tuple[int, int], list[np.ndarray]]:
    """(width, height) and the decoded RGB frames of an MP4."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    frames = [np.frombuffer(data, np.uint8).reshape(height, width, 3) for data in reader]
    return (width, height), frames


def read_gif(path: Path) -> tuple[tuple[int, int], list[np.ndarray]]:
    """(width, height) and the decoded RGB frames of a GIF."""
    with Image.open(path) as image:
        frames = []
        for index in range(image.n_frames):
            image.seek(index)
            frames.append(np.asarray(image.convert("RGB")))
        return image.size, frames


def test_frames_per_episode_matches_hand_counts() -> None:
    # 6 steps, every step: 0..6 -> 7 frames; every 4th: 0, 4 and the last, 6 -> 3; 8 steps every 4th: 0, 4, 8 -> 3
    assert frames_per_episode(6, 1) == 7
    assert frames_per_episode(6, 4) == 3
    assert frames_per_episode(8, 4) == 3
    assert frames_per_episode(10, 4) == 4  # 0, 4, 8, 10
    assert frames_per_episode(3, 5) == 2  # 0 and the last, 3


# Captions ------------------------------------------------------------------------------------------------------------


def fake_state(step: int, goal_distance: float = 4.25) -> TeamState:
    """Two agents whose centroid is ``goal_distance`` m left of the goal, with known errors."""
    zeros = np.zeros(2)
    return TeamState(
        step=step,
        positions=np.array([[1.0, 2.0], [3.0, 2.0]]),  # centroid (2, 2)
        velocities=np.zeros((2, 2)),
        goal=np.array([2.0 + goal_distance, 2.0]),
        obstacles=np.zeros((0, 3)),
        neighbours=np.array([[1, 1], [0, 0]]),
        contacts_agent=zeros,
        contacts_obstacle=zeros,
        angle_errors_deg=np.array([10.0, 14.6]),
        bearing_errors=np.array([0.1, 0.2]),
        neighbour_distance_errors=np.array([0.5, 0.0]),
        centroid=np.array([2.0, 2.0]),
        goal_distance=goal_distance,
    )


CONFIG = SimpleNamespace(max_steps=100, eta_g=0.4)


def test_caption_after_a_step_shows_the_mean_errors() -> None:
    assert episode_caption(3, fake_state(120), SimpleNamespace(max_steps=2500, eta_g=0.4)) == [
        "episode 3   step 120 / 2500",
        "running",
        "angle error 12.3 deg",  # (10 + 14.6) / 2
        "bearing error 0.150",
        "neighbour distance error 0.25 m",
        "goal distance 4.25 m",
    ]


def test_caption_at_reset_shows_no_errors() -> None:
    caption = episode_caption(0, fake_state(0), CONFIG)
    assert caption[:2] == ["episode 0   step 0 / 100", "running"]
    assert caption[2:5] == ["angle error -", "bearing error -", "neighbour distance error -"]
    assert caption[5] == "goal distance 4.25 m"


@pytest.mark.parametrize(
    ("step", "success", "status"),
    [(99, False, "running"), (100, False, "time-out"), (57, True, "success"), (100, True, "success")],
)
def test_caption_status(step: int, success: bool, status: str) -> None:
    """Success: the centroid within eta_g (0.4 m) of the goal; time-out: T_s steps without it."""
    assert episode_caption(1, fake_state(step, 0.3 if success else 4.25), CONFIG)[1] == status


def test_overlay_changes_the_top_left_box_only() -> None:
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, size=(120, 200, 3), dtype=np.uint8)
    original = frame.copy()
    overlaid = overlay_text(frame, ["episode 1", "running"], font_size=12, margin=5)
    assert overlaid.shape == frame.shape and overlaid.dtype == np.uint8
    np.testing.assert_array_equal(frame, original)  # the input is left alone
    changed = (overlaid != frame).any(axis=2)
    rows, columns = np.flatnonzero(changed.any(axis=1)), np.flatnonzero(changed.any(axis=0))
    assert rows[0] == 5 and columns[0] == 5  # the box starts at the margin
    assert rows[-1] < 60 and columns[-1] < 100  # two short lines of 12 px text stay in the top-left quarter
    box = changed[rows[0] : rows[-1] + 1, columns[0] : columns[-1] + 1]
    assert box.mean() > 0.95  # the whole box is whitened (but a pixel or two of random noise may already be right)
    # the box is lighter than the frame under it, and the text is dark
    assert overlaid[changed].astype(int).mean() > frame[changed].astype(int).mean()
    assert overlaid[rows[0] : rows[-1], columns[0] : columns[-1]].min() < 60
    np.testing.assert_array_equal(overlay_text(frame, []), frame)


def test_overlay_rejects_other_images() -> None:
    with pytest.raises(ValueError, match="uint8"):
        overlay_text(np.zeros((10, 10, 3)), ["float"])


# Writers -------------------------------------------------------------------------------------------------------------


def gradient_frames(count: int, width: int, height: int) -> list[np.ndarray]:
    """Frames of few colours that differ from one another (a moving block on a grey background)."""
    frames = []
    for index in range(count):
        frame = np.full((height, width, 3), 200, np.uint8)
        frame[:, index * 3 : index * 3 + 10] = (200, 40, 40)
        frames.append(frame)
    return frames


def test_gif_frames_are_exact(tmp_path: Path) -> None:
    frames = gradient_frames(6, 41, 30)
    path = tmp_path / "nested" / "block.gif"
    assert write_video(iter(frames), path, fps=20) == 6
    size, decoded = read_gif(path)
    assert size == (41, 30) and len(decoded) == 6
    for got, want in zip(decoded, frames):
        np.testing.assert_array_equal(got, want)
    with Image.open(path) as image:
        assert image.info["duration"] == 50 and image.info["loop"] == 0  # ms per frame at 20 fps; loop forever
    assert sorted(p.name for p in path.parent.iterdir()) == ["block.gif"]  # no temporary left


def test_gif_merges_a_repeated_frame_into_a_longer_one(tmp_path: Path) -> None:
    """Pillow stores an unchanged frame as more time on the previous one: the animation plays the same."""
    frames = gradient_frames(3, 41, 30)
    frames.insert(2, frames[1])
    path = tmp_path / "repeat.gif"
    assert write_video(frames, path, fps=20) == 4
    durations = []
    with Image.open(path) as image:
        for index in range(image.n_frames):
            image.seek(index)
            durations.append(image.info["duration"])
    assert durations == [50, 100, 50]


def test_mp4_pads_odd_sizes(tmp_path: Path) -> None:
    path = tmp_path / "block.mp4"
    frames = gradient_frames(5, 41, 31)
    assert write_video(frames, path, fps=10) == 5
    size, decoded = read_mp4(path)
    assert size == (42, 32) and len(decoded) == 5
    assert imageio_ffmpeg.count_frames_and_secs(str(path)) == (5, pytest.approx(0.5, abs=0.11))
    for got, want in zip(decoded, frames):
        assert np.abs(got[:31, :41].astype(int) - want).mean() < 6  # a 10 px red block: chroma at half resolution


@pytest.mark.parametrize("name", ["clip.avi", "clip", "clip.mp4.part"])
def test_unknown_suffixes_are_refused(tmp_path: Path, name: str) -> None:
    suffix = Path(name).suffix
    with pytest.raises(ValueError, match=rf"unknown suffix '{suffix}'.*\.mp4.*\.gif"):
        VideoWriter(tmp_path / name)
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_bad_frames_and_cleans_up(tmp_path: Path) -> None:
    path = tmp_path / "bad.gif"
    path.write_bytes(b"an older video")
    with pytest.raises(ValueError, match="first was 20x10"), VideoWriter(path) as writer:
        writer.append(np.zeros((10, 20, 3), np.uint8))
        writer.append(np.zeros((10, 21, 3), np.uint8))
    assert path.read_bytes() == b"an older video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.gif"]
    with pytest.raises(ValueError, match="no frames"):
        write_video([], tmp_path / "empty.mp4")
    assert not (tmp_path / "empty.mp4").exists()
    with pytest.raises(ValueError, match="fps"):
        VideoWriter(tmp_path / "fast.gif", fps=60)


# render_episodes -----------------------------------------------------------------------------------------------------


def test_render_gif_holds_every_captioned_frame(tmp_path: Path, normalised: SimpleNamespace) -> None:
    path = tmp_path / "episodes.gif"
    written = render_episodes(
        still_model(normalised), path, episodes=2, stage=3, seed=5, env_overrides={"max_steps": MAX_STEPS}
    )
    assert written == 2 * (MAX_STEPS + 1)
    config = normalised.config.replace(stage=3, max_steps=MAX_STEPS)
    want = expected_frames(config, episodes=2, seed=5)
    size, decoded = read_gif(path)
    assert len(decoded) == len(want) == written
    assert size == (want[0].shape[1], want[0].shape[0]) == (900, 600)  # 15 m x 10 m at 60 px/m
    assert decoded[0].std() > 10  # not blank
    for got, frame in zip(decoded, want):
        np.testing.assert_array_equal(got, frame)  # few colours: the palette is exact


def test_render_mp4_keeps_every_nth_frame_and_each_last(tmp_path: Path, normalised: SimpleNamespace) -> None:
    path = tmp_path / "episodes.mp4"
    written = render_episodes(
        still_model(normalised), path, episodes=2, seed=1, fps=10, frame_every=4, env_overrides={"max_steps": 10}
    )
    assert written == 2 * 4  # steps 0, 4, 8 and 10 of each episode
    nframes, seconds = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert nframes == 8 and seconds == pytest.approx(0.8, abs=0.11)
    size, decoded = read_mp4(path)
    assert size == (900, 600) and len(decoded) == 8
    want = expected_frames(normalised.config.replace(stage=3, max_steps=10), episodes=2, seed=1, frame_every=4)
    assert len(want) == 8
    assert decoded[0].std() > 10
    differences = [np.abs(got.astype(int) - frame).mean() for got, frame in zip(decoded, want)]
    # H.264 at crf 18 in limited-range yuv420p: flat colours come back within ~2 levels (1.7 on average measured)
    assert max(differences) < 3.0
    # each frame is closer to its own expected frame than to the other episode's
    assert np.abs(decoded[0].astype(int) - want[4]).mean() > 2 * differences[0]


def test_failure_midway_leaves_no_file(tmp_path: Path, normalised: SimpleNamespace) -> None:
    for suffix in (".mp4", ".gif"):
        path = tmp_path / "out" / f"failed{suffix}"
        with pytest.raises(RuntimeError, match="scripted failure on call 3"):
            render_episodes(still_model(normalised, fail_on_call=3), path, env_overrides={"max_steps": MAX_STEPS})
        assert not path.exists()
    assert list((tmp_path / "out").iterdir()) == []


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"episodes": 0}, "episodes must be >= 1"),
        ({"fps": 0}, "fps must be >= 1"),
        ({"frame_every": 0}, "frame_every must be >= 1"),
        ({"path_name": "video.webm"}, "unknown suffix '.webm'"),
        ({"env_overrides": {"n_agents": 4}}, "does not fit"),
    ],
)
def test_render_refuses_bad_arguments(
    tmp_path: Path, normalised: SimpleNamespace, arguments: dict[str, Any], message: str
) -> None:
    path = tmp_path / arguments.pop("path_name", "video.mp4")
    model = still_model(normalised)
    with pytest.raises(ValueError, match=message):
        render_episodes(model, path, **arguments)
    assert model.model.calls == 0
    assert list(tmp_path.iterdir()) == []


def test_gif_of_many_colours_is_quantised(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    smooth = np.linspace(0, 255, 64 * 48).reshape(48, 64, 1)
    frames = [np.clip(smooth + rng.normal(0, 3, (48, 64, 3)) + shift, 0, 255).astype(np.uint8) for shift in (0, 20)]
    assert len(np.unique(frames[0].reshape(-1, 3), axis=0)) > 256
    path = tmp_path / "many.gif"
    assert write_video(frames, path, fps=5) == 2
    size, decoded = read_gif(path)
    assert size == (64, 48) and len(decoded) == 2
    for got, want in zip(decoded, frames):
        assert np.abs(got.astype(int) - want).mean() < 8


def test_render_can_draw_the_lidar(tmp_path: Path, normalised: SimpleNamespace) -> None:
    first = {}
    for draw_lidar in (False, True):
        path = tmp_path / f"lidar_{draw_lidar}.gif"
        assert render_episodes(still_model(normalised), path, env_overrides={"max_steps": 1}, draw_lidar=draw_lidar) == 2
        first[draw_lidar] = read_gif(path)[1][0]
    assert (first[True] != first[False]).any(axis=2).sum() > 100  # the rays that hit something


def test_a_gif_is_written_as_its_frames_come(tmp_path: Path) -> None:
    """Frame k reaches the file when frame k + 1 comes (one frame is held back to merge repeats), so a 2500-step episode
    is never held in memory."""
    sizes = []
    with VideoWriter(tmp_path / "long.gif", fps=20) as writer:
        for frame in gradient_frames(12, 60, 20):
            writer.append(frame)
            (temporary,) = tmp_path.glob(".long.*.tmp.gif")
            sizes.append(temporary.stat().st_size)
    assert sizes[0] == 0 and all(later > earlier for earlier, later in itertools.pairwise(sizes[1:]))
    with Image.open(tmp_path / "long.gif") as image:
        assert image.n_frames == 12
