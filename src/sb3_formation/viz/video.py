"""Videos of evaluation episodes: rendered team states with a caption, streamed to an MP4 or a GIF.

MP4 files are H.264 (``yuv420p``) written through the ffmpeg binary of ``imageio-ffmpeg``, frame by frame; GIFs are
written frame by frame with Pillow's GIF helpers (a 2500-step episode is never held in memory). Either way the video
goes to a temporary file beside the target, which replaces the target only once the encoder has finished it without
error (ffmpeg's exit status is checked): a failure, a full disk included, leaves the earlier video as it was and no
temporary file.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import subprocess
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import IO, Any, cast

import numpy as np
import torch
from PIL import GifImagePlugin, Image, ImageDraw, ImageFont
from tqdm.auto import tqdm

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.rendering import render_frame
from sb3_formation.env.scenes import scenes_named
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.rollouts import PlayJob, episode_config, play_episodes, seed_policy
from sb3_formation.utils.files import replace_with, temporary_beside

#: File suffixes :class:`VideoWriter` can write.
VIDEO_SUFFIXES = (".mp4", ".gif")
#: GIF frame delays are whole centiseconds and browsers slow down delays under 2 cs: GIFs play at most 50 fps.
GIF_MAX_FPS = 50


# Captions ------------------------------------------------------------------------------------------------------------


#: A drawing context to measure text with.
_MEASURE = ImageDraw.Draw(Image.new("RGB", (1, 1)))


@functools.lru_cache(maxsize=8)
def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """Pillow's default font at ``size`` px (a fixed-size bitmap font when Pillow was built without FreeType)."""
    return ImageFont.load_default(size=size)


def overlay_text(
    frame: np.ndarray, lines: Sequence[str], font_size: int = 16, margin: int = 8, opacity: float = 0.75
) -> np.ndarray:
    """Write ``lines`` in black in the top-left corner of ``frame``, on a semi-opaque white box.

    :param frame: ``(H, W, 3)`` uint8 image (not modified)
    :param lines: text lines, top to bottom
    :param font_size: font height (px)
    :param margin: gap between the frame's corner and the box, and between the box's border and the text (px)
    :param opacity: opacity of the white box, in [0, 1]
    :return: a new ``(H, W, 3)`` uint8 image; only the box's pixels differ from ``frame``
    """
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"frame must be an (H, W, 3) uint8 array, got shape {frame.shape} and dtype {frame.dtype}")
    if not 0.0 <= opacity <= 1.0:
        raise ValueError(f"opacity must be in [0, 1], got {opacity}")
    output = frame.copy()
    if not lines:
        return output
    text, font, corner = "\n".join(lines), _font(font_size), (margin, margin)
    _, _, right, bottom = _MEASURE.multiline_textbbox(corner, text, font=font, spacing=4)
    height, width = frame.shape[:2]
    box_bottom, box_right = min(math.ceil(bottom) + 2 * margin, height), min(math.ceil(right) + 2 * margin, width)
    if box_bottom <= margin or box_right <= margin:  # a frame too small for any box
        return output
    box = output[margin:box_bottom, margin:box_right].astype(np.float32)
    image = Image.fromarray(np.rint(box + opacity * (255.0 - box)).astype(np.uint8))
    ImageDraw.Draw(image).multiline_text(corner, text, fill=(0, 0, 0), font=font, spacing=4)
    output[margin:box_bottom, margin:box_right] = np.asarray(image)
    return output


def episode_caption(episode: int, state: TeamState, config: FormationConfig) -> list[str]:
    """Caption lines of a frame: episode and step, outcome, the agents' mean formation errors, goal distance.

    :param episode: evaluation episode index
    :param state: the team's state shown by the frame (errors are shown as "-" right after the reset)
    :param config: the task configuration (goal radius, episode length)
    """
    if state.step > 0 and state.goal_distance <= config.eta_g:
        status = "success"
    elif state.step >= config.max_steps:
        status = "time-out"
    else:
        status = "running"

    def error(values: np.ndarray, digits: int, unit: str = "") -> str:
        return "-" if state.step == 0 else f"{float(np.mean(values)):.{digits}f}{unit}"

    return [
        f"episode {episode}   step {state.step} / {config.max_steps}",
        status,
        f"angle error {error(state.angle_errors_deg, 1, ' deg')}",
        f"bearing error {error(state.bearing_errors, 3)}",
        f"neighbour distance error {error(state.neighbour_distance_errors, 2, ' m')}",
        f"goal distance {state.goal_distance:.2f} m",
    ]


# Writers -------------------------------------------------------------------------------------------------------------


def _check_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"cannot write a video to {path}: unknown suffix {path.suffix!r}, use one of {VIDEO_SUFFIXES}")
    return suffix


class _Mp4Stream:
    """H.264 frames piped to the ffmpeg binary of ``imageio-ffmpeg``, which writes ``path``; odd frame sizes are padded
    to even ones (repeating the last row or column). ffmpeg's own messages go to stderr.

    :param path: the file ffmpeg writes
    :param size: (width, height) of the frames (px)
    :param fps: frames per second
    :param crf: H.264 constant rate factor
    :param target: the video's name in messages
    """

    def __init__(self, path: Path, size: tuple[int, int], fps: int, crf: int, target: Path) -> None:
        try:
            import imageio_ffmpeg
        except ImportError as error:
            raise ImportError("writing .mp4 videos needs imageio-ffmpeg: pip install imageio-ffmpeg") from error
        width, height = size
        self.pad = ((0, height % 2), (0, width % 2), (0, 0))
        self.target = target
        raw = ["-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width + width % 2}x{height + height % 2}", "-r", str(fps)]
        h264 = ["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", str(crf), "-movflags", "+faststart"]
        command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", *raw, "-i", "-", "-an", *h264, str(path)]
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
        self.stdin = cast(IO[bytes], self.process.stdin)  # a pipe (stdin=PIPE), never None

    def write(self, frame: np.ndarray) -> None:
        frame = np.pad(frame, self.pad, mode="edge") if any(after for _, after in self.pad) else frame
        try:
            self.stdin.write(np.ascontiguousarray(frame).data)
        except OSError:  # a broken pipe: ffmpeg stopped
            status = self.process.wait()
            raise RuntimeError(f"ffmpeg stopped writing {self.target} (exit status {status}; its message is above)") from None

    def close(self) -> None:
        """Let ffmpeg finish the file and wait for it.

        :raises RuntimeError: ffmpeg failed (e.g. a full disk); its message is on stderr
        """
        with contextlib.suppress(OSError):  # a broken pipe: the exit status tells
            self.stdin.close()
        status = self.process.wait()
        if status != 0:
            raise RuntimeError(f"ffmpeg failed writing {self.target} (exit status {status}; its message is above)")

    def kill(self) -> None:
        """Stop ffmpeg without finishing the file."""
        self.process.kill()
        with contextlib.suppress(OSError):
            self.stdin.close()
        self.process.wait()


class _GifStream:
    """Frames quantised to a palette each (median cut: exact for the env's renderings, which have fewer than 256
    colours) and written to ``path`` as they come, each with its own colour table, through Pillow's frame-by-frame GIF
    helpers (``GifImagePlugin.getheader`` and ``getdata``). One frame is held back: a frame equal to it becomes more time
    on it, as Pillow's own writer merges them.

    Frame k is shown for round(100 (k + 1) / fps) - round(100 k / fps) cs, so the total length is exact.
    """

    def __init__(self, path: Path, fps: int) -> None:
        self.fps = fps
        self.frames = 0
        self.file: IO[bytes] = open(path, "wb")  # closed by close or kill
        self.held: tuple[np.ndarray, Image.Image, int] | None = None  # a frame not written yet, its image and delay

    def write(self, frame: np.ndarray) -> None:
        k = self.frames
        delay = round(100 * (k + 1) / self.fps) - round(100 * k / self.fps)  # centiseconds
        self.frames += 1
        if self.held is not None and np.array_equal(self.held[0], frame):
            self.held = (self.held[0], self.held[1], self.held[2] + delay)
            return
        self._write_held()
        image = Image.fromarray(frame).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        self.held = (frame.copy(), image, delay)

    def _write_held(self) -> None:
        if self.held is None:
            return
        _, image, delay = self.held
        if self.file.tell() == 0:
            header, _ = GifImagePlugin.getheader(image, info={"loop": 0})
            self.file.write(b"".join(header))
        for chunk in GifImagePlugin.getdata(image, duration=10 * delay, include_color_table=True):
            self.file.write(chunk)
        self.file.flush()  # to the file now, not at the end
        self.held = None

    def close(self) -> None:
        with self.file:
            self._write_held()
            self.file.write(b";")  # the GIF trailer

    def kill(self) -> None:
        """Stop writing (the caller deletes the file)."""
        self.file.close()


class VideoWriter:
    """Stream ``(H, W, 3)`` uint8 frames into an ``.mp4`` (H.264) or ``.gif`` file; use as a context manager.

    Frames go to a temporary file in the target's folder (created if needed), which replaces ``path`` on
    :meth:`close` once the encoder has finished it without error; :meth:`abort`, an exception inside the ``with`` block
    or a failing encoder (ffmpeg's exit status, a full disk) deletes it and leaves ``path`` as it was.
    Every frame must have the size of the first. MP4 frames of odd width or height are padded by one pixel.

    :param path: target file; its suffix picks the format (one of :data:`VIDEO_SUFFIXES`)
    :param fps: frames per second (at most :data:`GIF_MAX_FPS` for a GIF)
    :param crf: H.264 constant rate factor of an MP4, 0 (lossless) to 51 (worst)
    """

    def __init__(self, path: str | os.PathLike[str], fps: int = 20, crf: int = 18) -> None:
        self.path = Path(path)
        self.suffix = _check_suffix(self.path)
        if fps < 1:
            raise ValueError(f"fps must be >= 1, got {fps}")
        if self.suffix == ".gif" and fps > GIF_MAX_FPS:
            raise ValueError(f"fps must be <= {GIF_MAX_FPS} for a GIF, got {fps}")
        if not 0 <= crf <= 51:
            raise ValueError(f"crf must be in [0, 51], got {crf}")
        self.fps, self.crf = fps, crf
        self.frames = 0  #: frames written so far
        self.size: tuple[int, int] | None = None  #: (width, height) of the frames (px), known after the first
        self._temporary: Path | None = temporary_beside(self.path)
        self._stream: _Mp4Stream | _GifStream | None = None

    def append(self, frame: np.ndarray) -> None:
        """Write one ``(H, W, 3)`` uint8 frame."""
        if self._temporary is None:
            raise RuntimeError(f"the video writer of {self.path} is closed")
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"frames must be (H, W, 3) uint8 arrays, got shape {frame.shape} and dtype {frame.dtype}")
        size = (frame.shape[1], frame.shape[0])
        if self._stream is None:
            self.size = size
            if self.suffix == ".gif":
                self._stream = _GifStream(self._temporary, self.fps)
            else:
                self._stream = _Mp4Stream(self._temporary, size, self.fps, self.crf, self.path)
        elif size != self.size:
            first = cast("tuple[int, int]", self.size)  # set with the stream
            raise ValueError(f"frame {self.frames} is {size[0]}x{size[1]} px, the first was {first[0]}x{first[1]}")
        self._stream.write(frame)
        self.frames += 1

    def close(self) -> None:
        """Finish the file and move it to ``path``; an error (or no frame at all) aborts instead.

        :raises RuntimeError: the encoder failed (``path`` is left as it was)
        :raises OSError: the file could not be written (e.g. a full disk; ``path`` is left as it was)
        """
        if self._temporary is None:
            return
        try:
            if self._stream is None:
                raise ValueError(f"no frames were written to {self.path}")
            stream, self._stream = self._stream, None
            stream.close()
            if self._temporary.stat().st_size == 0:
                raise RuntimeError(f"the encoder wrote nothing for {self.path}")
            replace_with(self._temporary, self.path)
            self._temporary = None
        finally:
            self.abort()

    def abort(self) -> None:
        """Stop writing and delete the temporary file; ``path`` is left untouched."""
        stream, self._stream = self._stream, None
        temporary, self._temporary = self._temporary, None
        try:
            if stream is not None:
                stream.kill()
        finally:
            if temporary is not None:
                temporary.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, traceback: Any) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike[str], fps: int = 20) -> int:
    """Write ``frames`` (``(H, W, 3)`` uint8, consumed one at a time) to an ``.mp4`` or ``.gif`` file.

    :param frames: the frames, all of one size
    :param path: target file, replaced only once the video is complete
    :param fps: frames per second
    :return: the number of frames written
    """
    with VideoWriter(path, fps) as writer:
        for frame in frames:
            writer.append(frame)
    return writer.frames


# Evaluation episodes -------------------------------------------------------------------------------------------------


def frames_per_episode(length: int, frame_every: int) -> int:
    """Frames :func:`render_episodes` keeps of an episode of ``length`` steps: steps 0, k, 2k, ... and the last one.

    :param length: steps played (>= 1)
    :param frame_every: keep every ``frame_every``-th step
    """
    return length // frame_every + 1 + (length % frame_every != 0)


def render_episodes(
    policy: TeamPolicy,
    path: str | os.PathLike[str],
    episodes: int = 1,
    stage: int = 3,
    seed: int = 0,
    deterministic: bool = True,
    fps: int = 20,
    frame_every: int = 1,
    env_overrides: dict[str, Any] | None = None,
    progress_bar: bool = False,
    draw_lidar: bool = False,
) -> int:
    """Play evaluation episodes on one team and write them, captioned, one after the other to a video file.

    Episode k is played from ``reset(seed=seed + k)`` as in :func:`~sb3_formation.experiment.evaluation.evaluate` (sampled
    actions are seeded with ``seed``, as with ``evaluate(..., n_envs=1)``); an episode of a crossing is the whole
    crossing of f formations, drawn from ``seed + f k`` and shown from its first formation. Of each episode the frames
    after steps 0, ``frame_every``, 2 ``frame_every``, ... and after its last step are kept (see
    :func:`frames_per_episode`); step 0 is the state after the reset.

    :param policy: the policy (a trained model with its normaliser, a controller, ...)
    :param path: ``.mp4`` or ``.gif`` file, replaced only once the video is complete
    :param episodes: number of episodes
    :param stage: curriculum stage of the scenarios
    :param seed: seed of the scenarios
    :param deterministic: use the policy's mean action
    :param fps: frames per second of the video
    :param frame_every: keep every ``frame_every``-th step (the video plays ``frame_every`` times faster)
    :param env_overrides: :class:`FormationConfig` fields to change from the policy's configuration
    :param progress_bar: show a tqdm progress bar of the episodes played
    :param draw_lidar: also draw the lidar rays
    :return: the number of frames written
    """
    for name, value in (("episodes", episodes), ("fps", fps), ("frame_every", frame_every)):
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    path = Path(path)
    _check_suffix(path)
    config = episode_config(policy.config, env_overrides, stage)
    unit = scenes_named(config.scenes).formations  # a crossing: its formations play together, its first one is shown
    job = PlayJob(
        policy=policy.fit(config),
        config=config,
        seed=seed,
        episodes=list(range(unit * episodes)),
        n_envs=unit,
        deterministic=deterministic,
        record=0,
    )
    with (
        VideoWriter(path, fps) as writer,
        tqdm(total=len(job.episodes), desc="rendering", unit="episode", disable=not progress_bar) as bar,
    ):

        def on_step(state: TeamState, episode: int) -> None:
            ended = state.step >= config.max_steps or (state.step > 0 and state.goal_distance <= config.eta_g)
            if episode % unit == 0 and (state.step % frame_every == 0 or ended):
                frame = render_frame(state, config, draw_lidar=draw_lidar)
                writer.append(overlay_text(frame, episode_caption(episode // unit, state, config)))

        with torch.random.fork_rng():
            seed_policy(job.policy, seed)
            play_episodes(job, on_episode=lambda: bar.update(1), on_step=on_step)
    return writer.frames
