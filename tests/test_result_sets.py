"""Result sets are written as a unit: an evaluation folder, a figure set and a video are complete and consistent, or
the earlier ones stay untouched, whatever fails (a full disk, a failing encoder, two writers at once), and no
temporary file is left behind."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import GifImagePlugin, Image

from sb3_formation import load_policy
from sb3_formation.cli import main
from sb3_formation.experiment.evaluation import (
    EPISODES_FILE,
    SUMMARY_FILE,
    TRAJECTORIES_FILE,
    EvaluationResult,
    evaluate,
    load_summary,
    load_trajectories,
    stored_summary,
)
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.targets import Target
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.utils.files import folder_lock
from sb3_formation.viz.plots import save_figures
from sb3_formation.viz.video import VideoWriter

RECIPE = ["--recipe", "ch4-individual"]
QUICK = ["--episodes", "2", "--n-envs", "2", "--no-progress"]
SEEDS = (0, 100, 1000)


@pytest.fixture(scope="module")
def results() -> dict[int, EvaluationResult]:
    """Short evaluations of the classical controller (no training needed), one per seed of :data:`SEEDS`."""
    policy = load_policy("controller:classical", recipe="ch4-individual")
    overrides = {"max_steps": 30}
    return {seed: evaluate(policy, 2, seed=seed, n_envs=2, env_overrides=overrides, record=2) for seed in SEEDS}


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file in ``folder`` (hidden ones included) with its bytes."""
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir()) if path.is_file()}


def hidden(folder: Path) -> list[str]:
    """Hidden files and folders left anywhere under ``folder`` (temporaries, lock files)."""
    return sorted(str(path.relative_to(folder)) for path in folder.rglob(".*"))


def full_disk_after(monkeypatch: pytest.MonkeyPatch, name_part: str, after: int = 8) -> None:
    """Make every write of a file whose name holds ``name_part`` write ``after`` bytes, then fail with ENOSPC."""
    write_bytes = Path.write_bytes

    def failing(path: Path, data: bytes | str) -> int:
        data = data.encode() if isinstance(data, str) else data
        if name_part not in path.name:
            return write_bytes(path, data)
        write_bytes(path, data[:after])
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(Path, "write_bytes", failing)
    monkeypatch.setattr(Path, "write_text", lambda path, text, *args, **kwargs: failing(path, text))


def check_whole_set(folder: Path, result: EvaluationResult) -> None:
    """``folder`` holds exactly the set of ``result``: its summary, its episode table and its trajectories."""
    summary = load_summary(folder)
    assert summary["seed"] == result.seed
    assert (folder / EPISODES_FILE).read_text() == result.episode_table()
    trajectories = load_trajectories(folder / TRAJECTORIES_FILE)
    np.testing.assert_array_equal(trajectories.seeds, result.trajectories.seeds)


# Evaluation folders --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("failing_file", [EPISODES_FILE, TRAJECTORIES_FILE, SUMMARY_FILE])
def test_full_disk_while_saving_an_evaluation_keeps_the_earlier_set(
    results: dict[int, EvaluationResult], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing_file: str
) -> None:
    folder = tmp_path / "eval"
    results[0].save(folder)
    before = snapshot(folder)
    with monkeypatch.context() as patch:
        full_disk_after(patch, Path(failing_file).stem)
        with pytest.raises(OSError, match="No space left"):
            results[100].save(folder)
    assert snapshot(folder) == before
    assert hidden(folder) == []
    check_whole_set(folder, results[0])


def test_evaluate_command_on_a_full_disk_exits_2_and_keeps_the_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "notes.txt").write_text("kept")  # --out may name a folder with other files: they are not of the set
    command = ["evaluate", "controller:classical", *RECIPE, *QUICK, "--trajectories", "1", "--out", str(folder)]
    assert main(command) == 0
    first = snapshot(folder)
    assert set(first) == {"notes.txt", SUMMARY_FILE, EPISODES_FILE, TRAJECTORIES_FILE}
    capsys.readouterr()
    with monkeypatch.context() as patch:
        full_disk_after(patch, Path(TRAJECTORIES_FILE).stem)
        assert main([*command, "--seed", "100"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "No space left on device" in error
    assert snapshot(folder) == first and hidden(folder) == []
    assert main([*command, "--seed", "100", "--trajectories", "0"]) == 0  # a set without trajectories drops the old
    assert set(snapshot(folder)) == {"notes.txt", SUMMARY_FILE, EPISODES_FILE}
    with pytest.raises(FileNotFoundError, match="no trajectories"):
        load_trajectories(folder / TRAJECTORIES_FILE)
    assert (folder / "notes.txt").read_text() == "kept" and hidden(folder) == []


def test_readers_refuse_a_mixed_set(
    results: dict[int, EvaluationResult], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A set mixed behind the writer's back (a kill between its renames, a hand copy) is refused, never read."""
    old, new = tmp_path / "old", tmp_path / "new"
    results[0].save(old)
    results[100].save(new)
    (old / TRAJECTORIES_FILE).write_bytes((new / TRAJECTORIES_FILE).read_bytes())
    with pytest.raises(ValueError, match=f"{TRAJECTORIES_FILE} is not of the evaluation"):
        load_trajectories(old / TRAJECTORIES_FILE)
    with pytest.raises(ValueError, match="is not of the evaluation"):
        load_summary(old)
    assert main(["plot", "trajectories", str(old), "--out", str(tmp_path / "t.png")]) == 2
    assert "is not of the evaluation" in capsys.readouterr().err and not list(tmp_path.glob("t*.png"))
    results[0].save(old)
    (old / EPISODES_FILE).write_text(results[100].episode_table())
    with pytest.raises(ValueError, match=f"{EPISODES_FILE} is not of the evaluation"):
        load_summary(old)
    (old / EPISODES_FILE).unlink()
    with pytest.raises(ValueError, match=f"{EPISODES_FILE} is not of the evaluation"):
        load_summary(old)
    assert Trajectories.load(old / TRAJECTORIES_FILE)  # the file itself is whole: only the set is mixed


def test_compare_does_not_reuse_a_mixed_set(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "controller:classical", *RECIPE, *QUICK]) == 0
    folder = tmp_path / "evaluations" / "controller-classical_ch4-individual"
    target, protocol = Target.parse("controller:classical", "ch4-individual"), EvaluationSection(episodes=2, seed=0)
    assert stored_summary(target, protocol) is not None
    with open(folder / EPISODES_FILE, "a") as stream:
        stream.write("a row of another evaluation\n")
    assert stored_summary(target, protocol) is None


def test_summaries_of_earlier_versions_are_read_unchecked(results: dict[int, EvaluationResult], tmp_path: Path) -> None:
    results[0].save(tmp_path)
    summary = json.loads((tmp_path / SUMMARY_FILE).read_text())
    del summary["files"]
    (tmp_path / SUMMARY_FILE).write_text(json.dumps(summary))
    (tmp_path / EPISODES_FILE).write_text("edited by hand\n")
    assert load_summary(tmp_path)["seed"] == 0
    assert len(load_trajectories(tmp_path / TRAJECTORIES_FILE)) == 2


def race(writers: list[Callable[[], object]]) -> list[BaseException]:
    """Run ``writers`` in threads released at once by one event; the errors they raised."""
    start, errors = threading.Event(), []

    def run(writer: Callable[[], object]) -> None:
        start.wait()
        try:
            writer()
        except BaseException as error:  # reported to the test
            errors.append(error)

    threads = [threading.Thread(target=run, args=(writer,)) for writer in writers]
    for thread in threads:
        thread.start()
    start.set()
    for thread in threads:
        thread.join()
    return errors


def test_evaluations_saved_into_one_folder_at_once_follow_each_other(
    results: dict[int, EvaluationResult], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each writer dawdles between its files, so that unserialised writers would interleave them."""
    save_trajectories = Trajectories.save

    def slow_save(self: Trajectories, path: Path) -> None:
        time.sleep(0.02)
        save_trajectories(self, path)

    monkeypatch.setattr(Trajectories, "save", slow_save)
    for round_ in range(3):
        folder = tmp_path / f"eval_{round_}"
        assert race([lambda result=result, folder=folder: result.save(folder) for result in results.values()]) == []
        last = load_summary(folder)["seed"]
        check_whole_set(folder, results[last])
        assert hidden(folder) == []


def test_a_folder_lock_held_too_long_is_one_line_error(tmp_path: Path) -> None:
    with folder_lock(tmp_path, "evaluation folder", remove=True):
        errors = race([lambda: folder_lock(tmp_path, "evaluation folder", wait=0.05).__enter__()])
    assert [str(error) for error in errors] == [
        f"evaluation folder {tmp_path} is in use by another process (pid {os.getpid()}); wait for it to end"
    ]
    assert hidden(tmp_path) == []  # removed by its holder on release


def test_a_lock_on_a_file_its_holder_deleted_is_taken_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A holder with ``remove`` deletes the lock file, then lets go: a waiter that opened the deleted file must not
    take that lock while a newcomer holds the new file's."""
    lock_file, real_flock, newcomer = tmp_path / ".lock", fcntl.flock, []

    def holder_lets_go_then_flock(fd: int, operation: int) -> None:
        if operation & fcntl.LOCK_EX and not newcomer:
            lock_file.unlink()  # the holder deletes the file this waiter opened and lets go...
            newcomer.append(open(lock_file, "a+"))  # ...and a newcomer locks the new file
            real_flock(newcomer[0].fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            newcomer[0].write("4242")
            newcomer[0].flush()
        real_flock(fd, operation)

    monkeypatch.setattr(fcntl, "flock", holder_lets_go_then_flock)
    with pytest.raises(RuntimeError, match=r"in use by another process \(pid 4242\)"):
        with folder_lock(tmp_path, "evaluation folder", wait=0.05):
            pass
    newcomer[0].close()


# Figure sets ---------------------------------------------------------------------------------------------------------


def figure(value: float) -> Figure:
    drawn = Figure(figsize=(2, 2))
    drawn.add_subplot().plot([0, 1], [0, value])
    return drawn


def test_full_disk_while_saving_a_figure_set_keeps_the_earlier_set(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "figures"
    names = [folder / "trajectory_000.png", folder / "trajectory_001.svg"]
    assert save_figures({name: figure(1.0) for name in names}) == names
    before = snapshot(folder)
    with monkeypatch.context() as patch:
        full_disk_after(patch, "trajectory_001")
        with pytest.raises(OSError, match="No space left"):
            save_figures({name: figure(2.0) for name in names})
    assert snapshot(folder) == before and hidden(folder) == []
    with pytest.raises(ValueError, match="one folder, got 2"):
        save_figures({folder / "a.png": figure(1.0), tmp_path / "b.png": figure(1.0)})
    assert save_figures({name: figure(2.0) for name in names}) == names
    assert all(snapshot(folder)[name.name] != before[name.name] for name in names)


# Videos --------------------------------------------------------------------------------------------------------------


FAILING_FFMPEG = {
    # reads every frame, then fails writing the end of the file: a broken file and exit status 1
    "at the trailer": 'for last; do :; done\ncat > /dev/null\nprintf broken > "$last"\n'
    'echo "Error writing trailer: No space left on device" >&2\nexit 1\n',
    # stops at once: the frames meet a closed pipe
    "at once": 'echo "No space left on device" >&2\nexit 1\n',
}


@pytest.fixture(params=sorted(FAILING_FFMPEG))
def failing_ffmpeg(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An ffmpeg binary that fails as named by the parameter."""
    script = tmp_path / "bin" / "ffmpeg"
    script.parent.mkdir()
    script.write_text("#!/bin/sh\n" + FAILING_FFMPEG[request.param])
    script.chmod(0o755)
    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(script))


def frames(count: int = 40, size: int = 96) -> list[np.ndarray]:
    return [np.full((size, size, 3), 10 * index % 256, np.uint8) for index in range(count)]


def test_failing_encoder_is_an_error_and_keeps_the_earlier_mp4(tmp_path: Path, failing_ffmpeg: None) -> None:
    folder = tmp_path / "videos"
    folder.mkdir()
    path = folder / "vid.mp4"
    path.write_bytes(b"a good older video")
    with pytest.raises(RuntimeError, match=r"ffmpeg (failed writing|stopped writing) .*vid\.mp4 \(exit status 1"):
        with VideoWriter(path, fps=10) as writer:
            for frame in frames():
                writer.append(frame)
    assert path.read_bytes() == b"a good older video"
    assert sorted(p.name for p in folder.iterdir()) == ["vid.mp4"]


def test_render_command_with_a_failing_encoder_exits_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], failing_ffmpeg: None
) -> None:
    monkeypatch.chdir(tmp_path)
    Path("vid.mp4").write_bytes(b"a good older video")
    command = ["render", "controller:classical", *RECIPE, "--max-steps", "5", "--out", "vid.mp4"]
    assert main(command) == 2
    output = capsys.readouterr()
    assert "frames written" not in output.out
    errors = [line for line in output.err.splitlines() if line.startswith("sb3-formation")]  # past the progress bar
    assert len(errors) == 1 and re.match(r"sb3-formation: error: ffmpeg (failed|stopped) writing vid\.mp4", errors[0])
    assert Path("vid.mp4").read_bytes() == b"a good older video"
    assert hidden(tmp_path) == []


def test_full_disk_while_writing_a_gif_keeps_the_earlier_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    Path("vid.gif").write_bytes(b"a good older gif")

    def full_disk_frame(image: Image.Image, *args: object, **options: object) -> list[bytes]:
        raise OSError(errno.ENOSPC, "No space left on device")  # the header is written, then the disk is full

    monkeypatch.setattr(GifImagePlugin, "getdata", full_disk_frame)
    with pytest.raises(OSError, match="No space left"), VideoWriter("vid.gif") as writer:
        for frame in frames(3):
            writer.append(frame)
    command = ["render", "controller:classical", *RECIPE, "--max-steps", "5", "--out", "vid.gif"]
    assert main(command) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert Path("vid.gif").read_bytes() == b"a good older gif"
    assert hidden(tmp_path) == []


def test_a_good_video_replaces_the_earlier_one(tmp_path: Path) -> None:
    """The checks above do not refuse a video that ffmpeg finishes: the real encoder's file takes the old one's place."""
    path = tmp_path / "vid.mp4"
    path.write_bytes(b"a good older video")
    with VideoWriter(path, fps=10) as writer:
        for frame in frames(5, 32):
            writer.append(frame)
    assert imageio_ffmpeg.count_frames_and_secs(str(path))[0] == 5
    assert hidden(tmp_path) == []
