"""Golden trajectories of the stepping engine: digests of every output of scripted runs, step by step.

The cases drive the public API only (``FormationVecEnv``, ``FormationEnv``, ``evaluate``), so the same script runs on
any commit. ``tests/data/engine_goldens.json`` holds the digests recorded from the code before the engine was
rewritten (the commit is named in the file); ``tests/test_engine.py`` replays every case and compares step by step.

Float results depend on the CPU's float kernels, so the digests are stored per
:func:`~sb3_formation.experiment.pretrained.numerics_fingerprint`. To add a CPU, record on it from the commit named in
the file: ``git worktree add /tmp/ref <commit>`` then ``PYTHONPATH=/tmp/ref/src python tests/engine_goldens.py``
from this checkout (the script merges the new fingerprint into the file). On a CPU without digests the tests compare
the first steps of each task with float values instead (:func:`early_steps`, recorded by ``python
tests/engine_goldens.py early`` on a CPU whose digests pass), within 1e-9.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

GOLDENS = Path(__file__).parent / "data" / "engine_goldens.json"
TASKS = ("ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing")
SIZES = tuple(range(3, 17))


#: Info and summary keys added after the goldens' commit, all zero in their cases (no moving obstacle): checked to be
#: zero, then left out of the digest, as the goldens were recorded without them.
ADDED_ZERO_KEYS = ("collisions_rammed",)


def digest(*parts: Any) -> str:
    """A short SHA-256 of values: arrays by dtype, shape and bytes, dicts key by key (SB3's wall-clock ``t`` left out,
    and :data:`ADDED_ZERO_KEYS` once checked to be zero), floats by ``repr`` (every bit)."""
    hasher = hashlib.sha256()

    def feed(value: Any) -> None:
        if isinstance(value, np.ndarray):
            hasher.update(f"{value.dtype}{value.shape}".encode())
            hasher.update(np.ascontiguousarray(value).tobytes())
        elif isinstance(value, dict):
            for key, item in value.items():
                if key in ADDED_ZERO_KEYS:
                    assert np.all(np.asarray(item) == 0), f"{key} is {item} where no obstacle moves"
                elif key != "t":
                    hasher.update(repr(key).encode())
                    feed(item)
        elif isinstance(value, (list, tuple)):
            hasher.update(b"[")
            for item in value:
                feed(item)
            hasher.update(b"]")
        else:
            hasher.update(repr(value).encode())

    for part in parts:
        feed(part)
    return hasher.hexdigest()[:16]


def goal_seeking_actions(observations: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """Every slot pushes towards the goal (its own observation's ``goal_offset``, indices 190-191) plus Gaussian
    noise, a third or so of it beyond [-1, 1]: teams reach goals, press on walls and touch each other."""
    offsets = observations[:, 190:192].astype(np.float64)
    norms = np.maximum(np.linalg.norm(offsets, axis=1, keepdims=True), 1e-9)
    return 0.8 * offsets / norms + rng.normal(0.0, noise, (len(observations), 2))


def vec_env_case(task: str, workers: int, fast: bool, team_critic: bool = False) -> list[str]:
    """A VecEnv of 14 teams of sizes 3-16 (a team critic: 6 teams of 3) over 150 steps with a stage change every 50
    steps, short episodes (terminations with ``fast`` physics, truncations always): one digest per step."""
    from sb3_formation import FormationConfig
    from sb3_formation.sb3.vec_env import FormationVecEnv

    overrides = {"stage": 1, "max_steps": 40 if fast else 45}
    if fast:
        overrides["v_max"] = 1.0
    config = FormationConfig.task(task, **overrides)
    sizes = [3] if team_critic else list(SIZES)
    n_teams = 6 if team_critic else len(SIZES)
    venv = FormationVecEnv(config, n_envs=n_teams, team_observations=team_critic, n_workers=workers, team_sizes=sizes)
    try:
        venv.seed(7)
        observations = venv.reset()
        digests = [digest(observations)]
        rng = np.random.default_rng(11)
        for step in range(150):
            if step in (50, 100):
                venv.env_method("set_stage", 2 if step == 50 else 3)
            actions = goal_seeking_actions(observations, rng, 1.0)
            observations, rewards, dones, infos = venv.step(actions)
            digests.append(digest(observations, rewards, dones, infos))
        digests.append(digest(venv.get_attr("stage"), venv.env_method("state")))
        return digests
    finally:
        venv.close()


def single_env_case(task: str, n_agents: int) -> list[str]:
    """One PettingZoo ``FormationEnv`` over 80 steps with an episode limit of 40 (resets with a seed, with none, and
    with a hand-made scenario), a stage change, ``state()``, the lidar of ``team_state()`` and a rendered frame."""
    from sb3_formation import FormationConfig, FormationEnv
    from sb3_formation.env.scenarios import Scenario

    env = FormationEnv(FormationConfig.task(task, n_agents=n_agents, stage=1, max_steps=40, v_max=1.0))
    observations, infos = env.reset(seed=3)
    digests = [digest(observations, infos, env.state())]
    rng = np.random.default_rng(5)
    for step in range(80):
        if step == 40:
            env.set_stage(3)
        stacked = np.stack([observations[agent] for agent in env.agents])
        actions = dict(zip(env.agents, goal_seeking_actions(stacked, rng, 1.0)))
        observations, rewards, terminated, truncated, infos = env.step(actions)
        team = env.team_state()
        digests.append(digest(observations, rewards, terminated, truncated, infos, env.state(), team.lidar_obstacles))
        if not env.agents:
            if step < 60:
                observations, infos = env.reset()
            else:
                positions = team.positions
                scenario = Scenario(
                    agent_positions=positions - positions.mean(axis=0) + [5.0, 5.0],
                    goal=np.array([9.0, 5.0]),
                    obstacles=np.array([[7.0, 5.5, 0.5]]),
                )
                observations, infos = env.reset(options={"scenario": scenario})
            digests.append(digest(observations, infos, env.state()))
    frame = FormationEnv(env.config, render_mode="rgb_array")
    frame.reset(seed=3)
    digests.append(digest(frame.render()))
    return digests


def evaluation_case(target: str, episodes: int, n_envs: int, workers: int, record: int) -> list[str]:
    """``evaluate`` of a controller or a shipped policy on stage 3 from seed 0: a digest per episode row (in episode
    order, then the recorded trajectories' arrays."""
    from sb3_formation import FormationConfig
    from sb3_formation.controllers.classical import ClassicalController
    from sb3_formation.experiment.evaluation import evaluate
    from sb3_formation.experiment.targets import load_policy

    if target == "controller:classical":
        policy = ClassicalController(FormationConfig.task("ch5-bearing"))
    else:
        policy = load_policy(target, device="cpu")
    result = evaluate(policy, episodes=episodes, stage=3, seed=0, n_envs=n_envs, n_workers=workers, record=record)
    digests = [digest(row) for row in result.episodes]
    trajectories = result.trajectories
    if trajectories is not None:
        # the arrays the reference commit records (it has no walls; the curriculum has none)
        assert trajectories.walls.shape[1] == 0
        digests.append(digest({name: value for name, value in vars(trajectories).items() if name not in ("config", "walls")}))
    return digests


def cases() -> Iterator[tuple[str, Callable[[], list[str]]]]:
    """Every case, by name; the same name with other worker counts must give the same digests."""
    for task in TASKS:
        for workers in (1, 2, 3):
            yield f"vec/{task}/fast/workers{workers}", lambda t=task, w=workers: vec_env_case(t, w, fast=True)
        yield f"vec/{task}/thesis-physics/workers1", lambda t=task: vec_env_case(t, 1, fast=False)
        for n_agents in (3, 6, 16):
            yield f"single/{task}/n{n_agents}", lambda t=task, n=n_agents: single_env_case(t, n)
    for workers in (1, 2):
        yield f"vec/ch4-team/team-critic/workers{workers}", lambda w=workers: vec_env_case("ch4-team", w, True, True)
    for workers in (1, 2):
        yield (
            f"evaluate/controller:classical/workers{workers}",
            lambda w=workers: evaluation_case("controller:classical", 12, 4, w, 3),
        )
    yield "evaluate/pretrained:ch5-bearing/workers1", lambda: evaluation_case("pretrained:ch5-bearing", 16, 8, 1, 2)


def case_name(name: str) -> str:
    """The name without its worker count: the cases that must agree."""
    return name.rsplit("/workers", 1)[0]


def record() -> None:
    """Play every case with the code on ``sys.path`` and merge its digests into :data:`GOLDENS` under this CPU's
    numerics fingerprint."""
    from sb3_formation.experiment.pretrained import numerics_fingerprint

    recorded: dict[str, list[str]] = {}
    for name, play in cases():
        if name.startswith("evaluate/") and not name.endswith("/workers1"):
            continue  # before the shared engine, each worker played its own share of the teams (the "team" column)
        digests = play()
        key = case_name(name)
        if key in recorded and recorded[key] != digests:
            raise SystemExit(f"{name} differs from another worker count of the same case")
        recorded[key] = digests
        print(f"{name}: {len(digests)} digests", flush=True)
    data = json.loads(GOLDENS.read_text()) if GOLDENS.is_file() else {}
    import sb3_formation

    code = Path(sb3_formation.__file__).parent
    commit = subprocess.run(["git", "-C", str(code), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    data.setdefault("recorded_from", commit)
    data.setdefault("by_numerics", {})[numerics_fingerprint()] = recorded
    GOLDENS.write_text(json.dumps(data, indent=1) + "\n")


#: The first steps of a team of each task, as float64 values (:func:`early_steps`), for CPUs without digests.
EARLY_STEPS = Path(__file__).parent / "data" / "engine_early_steps.npz"
#: Steps :func:`early_steps` plays: a perturbation of 1e-15 in the actions grows to about 1e-13 over 400 such steps
#: (measured), so another CPU's rounding stays far inside the tests' tolerance of 1e-9 over these.
EARLY_STEP_COUNT = 200


def early_steps(task: str) -> np.ndarray:
    """A team of 6 of ``task`` at stage 3 (seed 3) under goal-seeking actions with noise (seed 5), one row per step:
    positions, velocities, rewards and each agent's observation summed (its lidar, neighbours, goal). Another CPU
    rounds floats otherwise, but over these few steps the values agree within 1e-9: what ``tests/test_engine.py``
    checks where no digest of this CPU is recorded."""
    from sb3_formation import FormationConfig, FormationEnv

    env = FormationEnv(FormationConfig.task(task, n_agents=6, stage=3))
    observations, _ = env.reset(seed=3)
    rng = np.random.default_rng(5)
    rows = []
    for _ in range(EARLY_STEP_COUNT):
        stacked = np.stack([observations[agent] for agent in env.agents]).astype(np.float64)
        actions = dict(zip(env.agents, goal_seeking_actions(stacked, rng, 1.0)))
        observations, rewards, _, _, _ = env.step(actions)
        team = env.team_state()
        sums = [float(np.sum(observations[agent], dtype=np.float64)) for agent in env.possible_agents]
        rows.append(np.concatenate([team.positions.ravel(), team.velocities.ravel(), list(rewards.values()), sums]))
    return np.array(rows)


def record_early_steps() -> None:
    """Write :data:`EARLY_STEPS` from the code on ``sys.path`` (on a CPU whose digests it reproduces)."""
    np.savez_compressed(EARLY_STEPS, **{task: early_steps(task) for task in TASKS})


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    record_early_steps() if sys.argv[1:] == ["early"] else record()
