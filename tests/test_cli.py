"""The ``sb3-formation`` command line."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np
import pytest
import torch
import yaml
from PIL import Image
from terminal import default_ctrl_c

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.cli import main
from sb3_formation.controllers import RandomController
from sb3_formation.experiment.rollouts import PlayJob, play_episodes
from sb3_formation.experiment.trajectories import Trajectories


def test_rollout_prints_episodes_and_saves_the_final_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "frames" / "final.png"
    arguments = ["rollout", "--recipe", "ch4-team", "--episodes", "2", "--max-steps", "40", "--seed", "3", "--json"]
    assert main([*arguments, "--out", str(tmp_path / "first.png")]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [line["episode"] for line in lines] == [0, 1]
    assert all(line["length"] == 40 and line["success"] is False for line in lines)
    assert main(["rollout", "--episodes", "1", "--max-steps", "10", "--out", str(out)]) == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (600, 900, 3) and image.std() > 5


def test_rollout_summary_matches_a_manual_episode() -> None:
    """The one episode loop (which ``sb3-formation rollout`` plays) against an episode played by hand."""
    config = FormationConfig.task("ch5-angle", stage=2, max_steps=25)
    job = PlayJob(RandomController(config, seed=1), config, seed=4, episodes=[0], n_envs=1, deterministic=False, record=0)
    (summary,), _ = play_episodes(job)
    twin = FormationEnv(config)
    observations, _ = twin.reset(seed=4)
    rng = np.random.default_rng(1)
    total, angles = 0.0, []
    while twin.agents:
        observations, rewards, _, _, infos = twin.step({agent: rng.uniform(-1.0, 1.0, 2) for agent in observations})
        total += sum(rewards.values()) / len(rewards)
        angles += [info["angle_error_deg"] for info in infos.values()]
    assert summary["length"] == 25 and summary["stage"] == 2
    assert summary["return"] == pytest.approx(total)
    assert summary["angle_error_deg"] == pytest.approx(np.mean(angles))
    assert summary["final_goal_distance"] == pytest.approx(twin.team_state().goal_distance)


def test_bad_input_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rollout", "--agents", "2", "--max-steps", "5"]) == 2
    assert "n_agents" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["rollout", "--bogus"])
    assert exit_info.value.code == 2
    assert "--bogus" in capsys.readouterr().err
    assert main(["rollout", "--recipe", "ch9"]) == 2
    assert "unknown recipe 'ch9'" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_a_device_this_machine_lacks_is_refused_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for device, message in [
        ("cuda", "device 'cuda': torch sees no CUDA GPU on this machine; use --device auto or cpu"),
        ("tpu9", "device must be auto, cpu, cuda or cuda:<index>, got 'tpu9'"),
        ("meta", "device must be auto, cpu, cuda or cuda:<index>, got 'meta'"),
    ]:
        assert main(["train", "--device", device, "--logdir", str(tmp_path / "runs"), "--iterations", "0,0,1"]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


# evaluate, plot, render and compare on real (tiny) training runs ------------------------------------------------------

TINY_RUN = {"base": "ch5-bearing", "policy": {"net_arch": {"pi": [16], "vf": [16]}}}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two seeds of a tiny ch5-bearing training run (3 iterations, small networks, 20-step episodes)."""
    folder = tmp_path_factory.mktemp("runs")
    config = folder / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY_RUN))
    for seed in (0, 1):
        arguments = ["train", "--recipe", str(config), "--iterations", "1,0,2", "--n-envs", "1", "--seed", str(seed)]
        assert main([*arguments, "--env", "max_steps=20", "--logdir", str(folder / "logs"), "--no-progress"]) == 0
    return sorted((folder / "logs").iterdir())


def evaluate_quietly(target: Path, *extra: str) -> int:
    return main(["evaluate", str(target), "--episodes", "3", "--n-envs", "2", "--no-progress", *extra])


def test_evaluate_writes_summary_episodes_and_trajectories(runs: list[Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert evaluate_quietly(runs[0], "--trajectories", "2") == 0
    output = capsys.readouterr().out
    assert "success rate 0.0% (95% CI 0.0% - 56.1%)" in output  # Wilson upper bound for 0 of 3: 3.8415 / 6.8415
    summary = json.loads((runs[0] / "eval" / "summary.json").read_text())
    assert summary["episodes"] == 3 and summary["stage"] == 3 and summary["seed"] == 0 and summary["deterministic"]
    assert summary["model"]["file"] == str(runs[0] / "final_model.zip")
    with open(runs[0] / "eval" / "episodes.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [int(row["episode"]) for row in rows] == [0, 1, 2] and all(row["length"] == "20" for row in rows)
    lengths = [float(row["length"]) for row in rows]
    assert summary["all_episodes"]["length"] == {"mean": 20.0, "std": 0.0} == {"mean": np.mean(lengths), "std": 0.0}
    assert Trajectories.load(runs[0] / "eval" / "trajectories.npz").episodes.tolist() == [0, 1]


def test_plot_draws_every_figure(runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for run in runs:
        assert evaluate_quietly(run) == 0
    assert main(["plot", "trajectories", str(runs[0]), "--episodes", "0,2", "--every", "5"]) == 0
    figures = runs[0] / "eval" / "figures"
    assert sorted(path.name for path in figures.iterdir()) == ["trajectory_000.png", "trajectory_002.png"]
    assert main(["plot", "errors", str(runs[0] / "eval"), "--out", str(tmp_path / "errors.svg")]) == 0
    assert (tmp_path / "errors.svg").read_text().lstrip().startswith("<?xml")
    assert main(["plot", "bars", *map(str, runs), "--labels", "a,b", "--over", "all", "--out", str(tmp_path / "b.pdf")]) == 0
    assert (tmp_path / "b.pdf").read_bytes().startswith(b"%PDF")
    assert main(["plot", "training", *map(str, runs), "--window", "2", "--out", str(tmp_path / "training.png")]) == 0
    for path in (figures / "trajectory_000.png", tmp_path / "training.png"):
        assert np.asarray(Image.open(path).convert("L")).std() > 10  # not blank
    assert "figure written to" in capsys.readouterr().out


def test_render_writes_a_video_of_the_episodes(runs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "video.gif"
    assert main(["render", str(runs[0]), "--episodes", "2", "--max-steps", "6", "--out", str(out), "--seed", "3"]) == 0
    assert Image.open(out).n_frames == 2 * 7  # each episode: its reset frame and 6 steps


def test_compare_prints_a_table_and_reuses_matching_evaluations(
    runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["compare", *map(str, runs), "--episodes", "3", "--n-envs", "2", "--labels", "seed 0,seed 1", "--no-progress"]
    arguments += ["--out", str(tmp_path / "compare.png"), "--table", str(tmp_path / "compare.md")]
    assert main(arguments) == 0
    assert main(arguments) == 0
    output = capsys.readouterr().out
    assert output.count("reusing") >= 2  # the second call reuses both runs' eval/
    table = (tmp_path / "compare.md").read_text().splitlines()
    assert table[0].startswith("| policy | episodes | success rate (95 % CI) |")
    assert table[2].startswith("| seed 0 | 3 | 0.0% (0.0% - 56.1%) |") and table[3].startswith("| seed 1 | 3 |")
    assert (tmp_path / "compare.png").is_file()
    assert main([*arguments, "--seed", "5"]) == 0  # another protocol: evaluated again
    assert "reusing" not in capsys.readouterr().out


def test_compare_checks_every_target_before_it_evaluates_any(
    runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A missing second target is named before the first is evaluated into its eval/."""
    assert main(["evaluate", str(runs[0]), "--episodes", "4", "--n-envs", "2", "--no-progress"]) == 0
    summary = (runs[0] / "eval" / "summary.json").read_bytes()
    missing = tmp_path / "missing_run"
    arguments = ["compare", str(runs[0]), str(missing), "--episodes", "2", "--force", "--out", str(tmp_path / "c.png")]
    assert main(arguments) == 2
    assert f"no model at {missing}" in capsys.readouterr().err
    assert (runs[0] / "eval" / "summary.json").read_bytes() == summary and not (tmp_path / "c.png").exists()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["evaluate", "{empty}"], "holds no final_model.zip and no checkpoint"),
        (["evaluate", "{run}", "--agents", "3"], "n_agents=6 in the model, 3 in the env"),
        (["plot", "histogram", "{run}"], "unknown figure 'histogram'"),
        (["plot", "training", "{empty}"], "config.yaml"),
        (["plot", "training", "{run}", "--labels", "x", "--window", "3", "--out", "{tmp}/t.jpg"], "jpg"),
        (["plot", "trajectories", "{empty}"], "no trajectories.npz in"),
        (["plot", "trajectories", "{run}", "--episodes", "9"], "episodes [9] were not recorded"),
        (["render", "{run}", "--out", "{tmp}/video.avi", "--max-steps", "2"], "avi"),
        (["compare", "{run}", "{run}"], "labels must differ"),
    ],
)
def test_bad_input_to_evaluation_commands_is_one_line(
    runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    (runs[0] / "eval").mkdir(exist_ok=True)
    if not (runs[0] / "eval" / "trajectories.npz").exists():
        assert evaluate_quietly(runs[0]) == 0
    capsys.readouterr()
    empty = tmp_path / "empty"
    empty.mkdir()
    names = {"run": str(runs[0]), "empty": str(empty), "tmp": str(tmp_path)}
    assert main([argument.format(**names) for argument in arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1 and "Traceback" not in error


class Command:
    """A command started as a terminal starts it (its own session, Ctrl-C's default action), its output read as it
    comes, so that a test acts when the command has printed a line, never after a fixed sleep.

    :param arguments: the command's arguments
    :param cwd: its working folder
    :param python: options of the interpreter (e.g. ``-X importtime``, which prints each import as it ends)
    """

    def __init__(self, arguments: list[str], cwd: Path, python: tuple[str, ...] = ()) -> None:
        self.process = subprocess.Popen(
            [sys.executable, *python, "-m", "sb3_formation.cli", *arguments],
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=default_ctrl_c,
        )
        self.lines: dict[str, list[str]] = {"stdout": [], "stderr": []}
        self.changed = threading.Condition()
        self.readers = [
            threading.Thread(target=self._read, args=(name, stream), daemon=True)
            for name, stream in (("stdout", self.process.stdout), ("stderr", self.process.stderr))
        ]
        for reader in self.readers:
            reader.start()

    def _read(self, name: str, stream: IO[str]) -> None:
        for line in stream:
            with self.changed:
                self.lines[name].append(line)
                self.changed.notify_all()

    def wait_for(self, stream: str, predicate: Callable[[str], bool], timeout: float = 240.0) -> None:
        """Return once a line of ``stream`` fulfils ``predicate`` (a hang guard of ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        with self.changed:
            while not any(predicate(line) for line in self.lines[stream]):
                assert self.process.poll() is None, f"it ended first: {''.join(self.lines['stderr'])[-2000:]}"
                assert time.monotonic() < deadline, "timed out"
                self.changed.wait(timeout=0.2)

    def ctrl_c(self, timeout: float = 30.0) -> tuple[float, list[str]]:
        """Ctrl-C (SIGINT to the whole process group, as a terminal sends it): the seconds to the exit, and the lines
        it wrote to stderr from then on."""
        with self.changed:
            before = len(self.lines["stderr"])
        os.killpg(self.process.pid, signal.SIGINT)
        started = time.monotonic()
        self.process.wait(timeout=timeout)
        seconds = time.monotonic() - started
        for reader in self.readers:
            reader.join(timeout=timeout)
        return seconds, self.lines["stderr"][before:]


def shown_lines(lines: list[str]) -> list[str]:
    """The lines a user reads: without progress bars and without ``-X importtime``'s report."""
    return [
        line.rstrip("\n")
        for line in lines
        if line.strip() and not re.match(r"\w+: +\d+%\|", line) and not line.startswith("import time:")
    ]


@pytest.mark.parametrize(
    "arguments",
    [
        ["evaluate", "controller:classical", "--episodes", "2000", "--workers", "2", "--n-envs", "4", "--no-progress"],
        ["evaluate", "controller:classical", "--episodes", "2000", "--n-envs", "4", "--no-progress"],
        ["render", "controller:classical", "--episodes", "50", "--out", "v.gif"],
        ["compare", "controller:classical", "controller:random", "--episodes", "2000", "--workers", "2"],
    ],
    ids=["evaluate-workers", "evaluate", "render", "compare-workers"],
)
def test_ctrl_c_ends_evaluations_at_once_with_one_line(arguments: list[str], tmp_path: Path) -> None:
    """Ctrl-C, once the command has said what it is about to do, ends ``evaluate``, ``render`` and ``compare``, with
    or without workers, with exit code 130 and one line. The bound here is a hang guard for a loaded machine; the
    promised 2 s is measured alone by ``benchmarks/interrupts.py``."""
    command = Command(arguments, tmp_path)
    command.wait_for("stdout", lambda line: line.startswith(("evaluating", "rendering", "comparing")))
    seconds, errors = command.ctrl_c()
    assert seconds < 30.0 and command.process.returncode == 130, shown_lines(errors)
    assert shown_lines(errors) == [f"sb3-formation: {arguments[0]} interrupted"], errors


def test_ctrl_c_again_while_the_command_ends_keeps_one_line_and_code_130(tmp_path: Path) -> None:
    """Ctrl-C pressed again and again once the command has been interrupted (while it ends, Python's shutdown
    included, where SIGINT's default action would kill it): still one line and exit code 130, never a death by
    signal."""
    command = Command(["evaluate", "controller:classical", "--episodes", "2000", "--no-progress"], tmp_path)
    command.wait_for("stdout", lambda line: line.startswith("evaluating"))
    try:
        while command.process.poll() is None:  # a zombie still takes signals: this ends once it has been reaped
            os.killpg(command.process.pid, signal.SIGINT)
            time.sleep(0.002)
    except ProcessLookupError:
        pass
    command.process.wait(timeout=30.0)
    for reader in command.readers:
        reader.join(timeout=30.0)
    assert command.process.returncode == 130, command.lines["stderr"]
    assert shown_lines(command.lines["stderr"]) == ["sb3-formation: evaluate interrupted"], command.lines["stderr"]


def imported(module: str) -> Callable[[str], bool]:
    """Whether a line is ``-X importtime``'s report that the import of ``module`` ended."""
    return lambda line: line.startswith("import time:") and line.rsplit("|", 1)[-1].strip() == module


#: Moments of a command's start-up: the end of the import of numpy (the first heavy import), of torch, of
#: Stable-Baselines3 and of Pymunk (``-X importtime`` reports each), then the line that says what it is about to do.
START_UP_MOMENTS = {
    "numpy imported": ("stderr", imported("numpy")),
    "torch imported": ("stderr", imported("torch")),
    "stable_baselines3 imported": ("stderr", imported("stable_baselines3")),
    "pymunk imported": ("stderr", imported("pymunk")),
    "said what it does": ("stdout", lambda line: line.startswith("evaluating")),
}


@pytest.mark.parametrize("moment", list(START_UP_MOMENTS))
def test_ctrl_c_at_any_moment_of_start_up_is_one_line(moment: str, tmp_path: Path) -> None:
    """Ctrl-C while the command still imports torch and the rest (the CLI takes Ctrl-C in hand before it imports
    them), or as it starts its work: exit code 130 and one line, never a traceback."""
    arguments = ["evaluate", "controller:classical", "--episodes", "2000", "--n-envs", "4", "--no-progress"]
    command = Command(arguments, tmp_path, python=("-X", "importtime"))
    stream, predicate = START_UP_MOMENTS[moment]
    command.wait_for(stream, predicate)
    _, errors = command.ctrl_c()
    assert command.process.returncode == 130, shown_lines(errors)
    assert shown_lines(errors) == ["sb3-formation: evaluate interrupted"], errors
    assert not (tmp_path / "evaluations").exists()  # nothing half written


def test_scenes_option_evaluates_plots_and_renders_a_family(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--scenes passage``: evaluate writes its set to its own folder (``..._<recipe>-passage``, the curriculum's
    left alone), with two walls in every recorded episode; plot finds it with the same option; render draws it."""
    monkeypatch.chdir(tmp_path)
    common = ["--episodes", "2", "--n-envs", "2", "--no-progress"]
    assert main(["evaluate", "controller:classical", *common, "--scenes", "passage", "--trajectories", "1"]) == 0
    folder = tmp_path / "evaluations" / "controller-classical_ch5-bearing-passage"
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["scenes"] == "passage" and summary["episodes"] == 2
    with np.load(folder / "trajectories.npz") as data:
        assert data["walls"].shape == (1, 2, 5)
    assert not (tmp_path / "evaluations" / "controller-classical_ch5-bearing").exists()
    assert main(["plot", "trajectories", "controller:classical", "--scenes", "passage", "--out", "t.png"]) == 0
    assert (tmp_path / "t_000.png").is_file()
    assert main(["plot", "trajectories", "controller:classical", "--scenes", "corridor"]) == 2
    assert "--scenes corridor` first" in capsys.readouterr().err
    arguments = ["render", "controller:classical", "--scenes", "trap", "--max-steps", "5", "--out", "v.gif"]
    assert main(arguments) == 0 and (tmp_path / "v.gif").is_file()


def test_a_filtered_evaluation_without_a_success_prints_its_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``safe:controller:classical`` in 5-step episodes succeeds in none: its summary has the filter's metrics over
    the (no) successful episodes as ``-``, in the file and on the screen."""
    recipe = tmp_path / "short.yaml"
    recipe.write_text(yaml.safe_dump({"base": "ch5-bearing", "env": {"max_steps": 5}}))
    arguments = ["evaluate", "safe:controller:classical", "--recipe", str(recipe), "--episodes", "2", "--n-envs", "2"]
    assert main([*arguments, "--no-progress", "--out", str(tmp_path / "eval")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "success rate 0.0% (95% CI 0.0% - 65.8%)" in lines[2]
    row = next(line for line in lines if line.strip().startswith("filter_changed_fraction"))
    assert row.split()[1] == "-"
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["successful_episodes"]["filter_changed_fraction"] == {"mean": None, "std": None}


LONG_NAME = "a" * 300


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["evaluate", "controller:classical", "--episodes", str(10**30)], "--episodes: must be an integer in [1, 100,000]"),
        (["evaluate", "controller:classical", "--n-envs", str(2**64)], "--n-envs: must be an integer in [1, 1,024]"),
        (["evaluate", "controller:classical", "--workers", str(2**64)], "--workers: must be an integer in [1, 1,024]"),
        (
            ["evaluate", "controller:classical", "--trajectories", str(10**20)],
            "record (--trajectories) must be in [0, 100]",
        ),
        (["evaluate", "controller:classical", "--agents", str(10**20)], "--agents: must be an integer in [1, 64]"),
        (["render", "controller:classical", "--max-steps", str(10**20)], "--max-steps: must be an integer in [1, 100,000]"),
        (["render", "controller:classical", "--fps", str(10**20)], "--fps: must be an integer in [1, 1,000]"),
        (["rollout", "--seed", str(2**64)], "--seed: must be an integer in [0, 4,294,967,295]"),
        (["benchmark", "controller:classical", "--episodes", str(10**30)], "--episodes: must be an integer in [1, 100,000]"),
        (["plot", "training", "x", "--window", str(10**30)], "--window: must be an integer in [1, 1,000,000]"),
        (["evaluate", "controller:classical", "--out", ""], "--out: the path is empty"),
        (["compare", "controller:classical", "controller:random", "--out", ""], "--out: the path is empty"),
        (["compare", "controller:classical", "controller:random", "--table", ""], "--table: the path is empty"),
        (["compare", "controller:classical", "controller:random", "--out", f"{LONG_NAME}.png"], "longer than 255 bytes"),
        (["compare", "controller:classical", "controller:random", "--out", "bars.jpg"], "cannot save a figure as 'jpg'"),
        (["render", "controller:classical", "--out", f"{LONG_NAME}.gif"], "longer than 255 bytes"),
        (["benchmark", "controller:classical", "--out", ""], "--out: the path is empty"),
        (["train", "--run-dir", "", "--iterations", "0,0,1"], "--run-dir: the path is empty"),
        (["train", "--logdir", "", "--iterations", "0,0,1"], "logdir is empty"),
        (["export", "controller:classical", "--onnx", ""], "--onnx: the path is empty"),
        (["rollout", "--out", ""], "--out: the path is empty"),
        (["plot", "bars", "controller:classical", "--out", ""], "--out: the path is empty"),
    ],
)
def test_counts_and_output_paths_are_checked_before_any_work(
    arguments: list[str], message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every count option has a documented maximum (a larger one overflowed a C integer) and every path a command
    writes to is checked as it is read (an empty one was the working folder; a name too long failed after the work):
    one line, exit code 2, nothing written."""
    monkeypatch.chdir(tmp_path)
    try:
        code = main(arguments)  # refused by the command
    except SystemExit as exit_info:  # or as the arguments are read
        code = exit_info.code
    assert code == 2
    error = capsys.readouterr().err
    assert error.startswith("sb3-formation: error: ") and error.count("\n") == 1 and message in error, error
    assert list(tmp_path.iterdir()) == []


def test_a_reader_that_leaves_early_ends_the_command_without_a_word(tmp_path: Path) -> None:
    """``sb3-formation recipes | head -1``: the reader closes the pipe; the command stops with the shell's code for
    SIGPIPE (141) and writes nothing to stderr (it wrote ``error: [Errno 32] Broken pipe``)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "sb3_formation.cli", "recipes"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert process.stdout is not None
    process.stdout.close()  # the reader left before the first line
    _, errors = process.communicate(timeout=300)
    assert process.returncode == 141 and errors == b"", errors
