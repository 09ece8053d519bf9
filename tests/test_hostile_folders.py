"""Folders and names someone hands a user: a planted lock link, labels and names that leave ``--out``, outputs into
the package's own folder, two commands into one folder. Each is refused with one line, or handled, and no file outside
the named folder changes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sb3_formation.cli import main
from sb3_formation.experiment.pretrained import PRETRAINED_DIR
from sb3_formation.utils.files import PACKAGE_FOLDER, folder_lock


def one_line_error(capsys: pytest.CaptureFixture[str], arguments: list[str]) -> str:
    """Run the CLI with ``arguments``; it must fail with exit code 2 and one line (refused by the command, or as the
    arguments are read). :return: the line"""
    try:
        code = main(arguments)
    except SystemExit as exit_info:
        code = exit_info.code
    assert code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "Traceback" not in error, error
    return error


@pytest.mark.parametrize("planted", ["link", "dangling link", "folder", "fifo"])
def test_a_planted_lock_is_refused_and_what_it_points_to_is_untouched(
    tmp_path: Path, planted: str, capsys: pytest.CaptureFixture[str]
) -> None:
    precious = tmp_path / "precious"
    precious.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    lock = out / ".lock"
    if planted == "link":
        lock.symlink_to(precious)
    elif planted == "dangling link":
        lock.symlink_to(tmp_path / "created")
    elif planted == "folder":
        lock.mkdir()
    else:
        os.mkfifo(lock)
    error = one_line_error(capsys, ["evaluate", "controller:classical", "--episodes", "2", "--out", str(out), "--no-progress"])
    assert f"{out}: its .lock is" in error
    assert precious.read_text() == "precious" and not (tmp_path / "created").exists()
    assert sorted(path.name for path in out.iterdir()) == [".lock"]


def test_a_lock_link_in_a_run_folder_someone_sent_is_refused(tmp_path: Path) -> None:
    """Through ``run/eval/.lock -> ../../file`` (evaluate of a received run) and ``run/.lock`` (train --resume)."""
    precious = tmp_path / "precious"
    precious.write_text("precious")
    for folder in (tmp_path / "run" / "eval", tmp_path / "run"):
        folder.mkdir(parents=True, exist_ok=True)
        (folder / ".lock").symlink_to(os.path.relpath(precious, folder))
        with pytest.raises(RuntimeError, match=r"its \.lock is a symbolic link; remove it"), folder_lock(folder, "run folder"):
            pass
    assert precious.read_text() == "precious"


@pytest.mark.parametrize("label", ["..", ".", ""])
def test_a_benchmark_label_that_leaves_out_is_refused_before_anything_is_written(
    tmp_path: Path, label: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "p" / "out"
    arguments = ["benchmark", "controller:classical", "--labels", label, "--out", str(out), "--episodes", "2"]
    assert "is not a single file name" in one_line_error(capsys, [*arguments, "--no-progress"])
    assert not (tmp_path / "p").exists()


def test_a_second_benchmark_into_one_folder_is_refused_and_the_first_keeps_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    arguments = ["benchmark", "controller:classical", "--out", str(out), "--episodes", "1", "--workers", "1"]
    with folder_lock(out, "benchmark folder"):  # as a benchmark running in another process holds it
        assert "is in use by another process" in one_line_error(capsys, [*arguments, "--no-progress"])
        assert sorted(path.name for path in out.iterdir()) == [".lock"]
    assert main([*arguments, "--no-progress"]) == 0
    capsys.readouterr()
    assert not (out / ".lock").exists()
    table = (out / "benchmark.md").read_text()
    assert "already holds files" in one_line_error(capsys, [*arguments, "--labels", "other", "--no-progress"])
    assert (out / "benchmark.md").read_text() == table and not (out / "other").exists()


def test_no_command_overwrites_the_shipped_policies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An ``--out`` inside the installed package, or a default folder there (evaluating a shipped policy's folder as a
    run), is refused before anything is evaluated; the stored evaluation stays byte for byte."""
    shipped = PRETRAINED_DIR / "ch5-bearing"
    stored = {
        path: path.read_bytes() for path in PACKAGE_FOLDER.rglob("*") if path.is_file() and "__pycache__" not in path.parts
    }
    for arguments in (
        ["evaluate", "pretrained:ch5-bearing", "--out", str(shipped / "eval")],
        ["evaluate", str(shipped)],
        ["render", "pretrained:ch5-bearing", "--out", str(shipped / "episodes.gif")],
        ["benchmark", "controller:classical", "--out", str(PACKAGE_FOLDER / "benchmark")],
        ["train", "--recipe", "fast-ch5-bearing", "--run-dir", str(PACKAGE_FOLDER / "runs" / "x")],
    ):
        error = one_line_error(capsys, [*arguments, "--episodes" if arguments[0] != "train" else "--seed", "1"])
        assert "is inside the installed package sb3_formation" in error, arguments
    after = {
        path: path.read_bytes() for path in PACKAGE_FOLDER.rglob("*") if path.is_file() and "__pycache__" not in path.parts
    }
    assert after == stored


def test_a_recipe_name_that_leaves_the_logdir_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run's folder is ``<logdir>/<recipe name>_...``: a ``name:`` with a separator would put it elsewhere."""
    (tmp_path / "escape.yaml").write_text("base: ch5-bearing\nname: ../../escaped\n")
    error = one_line_error(capsys, ["train", "--recipe", str(tmp_path / "escape.yaml"), "--logdir", str(tmp_path / "a" / "b")])
    assert "recipe name '../../escaped' is not a single file name" in error
    assert sorted(path.name for path in tmp_path.iterdir()) == ["escape.yaml"]


def test_benchmark_labels_that_are_not_utf8_are_refused_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Bytes the shell passed through that are not UTF-8 (``--labels $'\\xff'``) were played through every scene set,
    then failed where the table is written, leaving a partial folder."""
    out = tmp_path / "out"
    label = os.fsdecode(b"caf\xe9")  # Latin-1, as a terminal of another encoding sends it
    arguments = ["benchmark", "controller:classical", "--labels", label, "--out", str(out), "--episodes", "2"]
    assert "is not valid UTF-8" in one_line_error(capsys, [*arguments, "--no-progress"])
    assert not out.exists()
