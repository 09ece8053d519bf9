"""Environment throughput: agent-steps per second of the VecEnv's batched stepping against team-by-team stepping and
the bare Pymunk step, in one run; with ``--reference REV``, the same benchmark of another commit right after.

ch5-bearing at stage 3, random actions, 90-ray lidar. Prints medians over repeats of:
- team by team: ``FormationEnv.step_array`` (each team an engine of its own) for one team after another with the
  VecEnv's bookkeeping (episode summaries, terminal observations, resets): the reference of the ratios;
- ``FormationVecEnv`` (one engine of every team) with every team in this process, and with ``n_workers=2`` (half the
  teams in this process, half in a worker process, through shared memory);
- one ``FormationEnv`` alone, and the bare Pymunk ``space.step`` of one team (sub-steps included);
- the batched VecEnv with every agent holding one action (pressed on walls, obstacles and each other), with contacts
  read from Pymunk's arbiters, and with a Python collision callback per contact added (the alternative).

Targets: with 14 teams of 6, at least 150,000 agent-steps/s on 2 cores (with 2 processes), and the batched VecEnv at
least 2.5x team-by-team stepping on one core. Against a reference commit (``--reference``), one ``FormationEnv`` at
least 0.9x its agent-steps/s and the VecEnv at least 1.0x.

Usage: ``python benchmarks/env_throughput.py [--steps 1000] [--repeats 5] [--teams 14] [--reference REV]``
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np
import pymunk
from reference import reference_checkout

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.world import World
from sb3_formation.sb3.vec_env import FormationVecEnv
from sb3_formation.utils.machine import machine_line

CONFIG = FormationConfig.task("ch5-bearing", stage=3)


def team_by_team_seconds(teams: int, steps: int, seed: int) -> float:
    """Seconds per team-step of ``teams`` envs stepped one after another, with what the VecEnv adds to each team."""
    envs = [FormationEnv(CONFIG) for _ in range(teams)]
    for index, env in enumerate(envs):
        env.reset(seed=seed + index)
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, teams * CONFIG.n_agents, 2))
    start = time.perf_counter()
    for step_actions in actions:
        observations, rewards, infos = [], [], []
        for team, env in enumerate(envs):
            rows = step_actions[team * CONFIG.n_agents : (team + 1) * CONFIG.n_agents]
            team_observations, team_rewards, terminated, truncated, team_infos = env.step_array(rows)
            if terminated or truncated:
                for info, terminal in zip(team_infos, team_observations):
                    info["terminal_observation"] = terminal
                team_infos[0]["formation_episode"] = env.episode_summary()
                team_observations = np.stack(list(env.reset()[0].values()))
            observations.append(team_observations)
            rewards.append(team_rewards)
            infos += team_infos
        np.concatenate(observations), np.concatenate(rewards).astype(np.float32)
    return (time.perf_counter() - start) / (steps * teams)


def vec_env_seconds(teams: int, steps: int, seed: int, workers: int, pressed: bool = False, callbacks: bool = False) -> float:
    """Seconds per team-step of ``FormationVecEnv`` (after a warm-up step that compiles and starts the workers).

    :param pressed: every agent holds one random action, so the agents press on the walls, obstacles and each other
    :param callbacks: also count contacts through a Python ``pre_solve`` callback per touching pair and sub-step (teams
        in this process only), as against reading them from Pymunk's arbiters
    """
    venv = FormationVecEnv(CONFIG, n_envs=teams, n_workers=workers)
    venv.seed(seed)
    venv.reset()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps + 1, venv.num_envs, 2))
    if pressed:
        actions[:] = actions[0]
    if callbacks:
        for env in venv.blocks.local.envs:
            env.world.space.on_collision(None, None, pre_solve=_record_contact)
    venv.step(actions[0])
    start = time.perf_counter()
    for step_actions in actions[1:]:
        venv.step(step_actions)
    elapsed = time.perf_counter() - start
    venv.close()
    return elapsed / (steps * teams)


_PAIRS: set[tuple[int, int]] = set()


def _record_contact(arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
    """The former contact count's work per touching pair and sub-step: the two shapes, as a pair in a set."""
    first, second = sorted(id(shape) for shape in arbiter.shapes)
    _PAIRS.add((first, second))


def pymunk_seconds(steps: int, seed: int) -> float:
    """Seconds of Pymunk's own ``space.step`` calls for one team-step (all sub-steps), agents moving at random."""
    env = FormationEnv(CONFIG)
    env.reset(seed=seed)
    world = World(CONFIG, env.scenario)
    rng = np.random.default_rng(seed)
    substep = CONFIG.dt / CONFIG.physics_substeps
    elapsed = 0.0
    for _ in range(steps):
        for body in world.agent_bodies:
            body.velocity = tuple(rng.uniform(-CONFIG.v_max, CONFIG.v_max, 2) / np.sqrt(2))
        start = time.perf_counter()
        for _ in range(CONFIG.physics_substeps):
            world.space.step(substep)
        elapsed += time.perf_counter() - start
    return elapsed / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--teams", type=int, default=14)
    parser.add_argument("--reference", help="a commit whose own env_throughput.py runs right after, for the ratios")
    args = parser.parse_args()
    print(machine_line())
    n, teams, steps = CONFIG.n_agents, args.teams, args.steps
    team_by_team_seconds(1, 5, 0)  # compile the kernels outside the timings
    # every measurement once per repeat, interleaved, so that each ratio sees the same machine
    rows: dict[str, list[float]] = {
        name: [] for name in ("team", "batched", "workers", "single", "pymunk", "pressed", "callbacks")
    }
    for seed in range(args.repeats):
        rows["team"].append(team_by_team_seconds(teams, steps, seed))
        rows["batched"].append(vec_env_seconds(teams, steps, seed, workers=1))
        rows["workers"].append(vec_env_seconds(teams, steps, seed, workers=2))
        rows["single"].append(team_by_team_seconds(1, steps, seed))
        rows["pymunk"].append(pymunk_seconds(steps, seed))
        rows["pressed"].append(vec_env_seconds(teams, steps, seed, workers=1, pressed=True))
        rows["callbacks"].append(vec_env_seconds(teams, steps, seed, workers=1, pressed=True, callbacks=True))
    median = {name: statistics.median(values) for name, values in rows.items()}

    def ratio(first: str, second: str) -> float:
        return statistics.median(a / b for a, b in zip(rows[first], rows[second]))

    print(
        f"Environment throughput, ch5-bearing stage 3, {teams} teams of n = {n}, {CONFIG.lidar_rays}-ray lidar, random actions"
    )
    print(f"medians of {args.repeats} repeats of {steps} steps")
    labels = {
        "team": "team by team, one core",
        "batched": "FormationVecEnv batched, one core",
        "workers": "FormationVecEnv batched, 2 processes",
        "single": "one FormationEnv alone",
    }
    for name, label in labels.items():
        print(f"  {label:36s}: {median[name] * 1e6:7.1f} us/team-step  {n / median[name]:10,.0f} agent-steps/s")
    print(
        f"  {'bare Pymunk space.step':36s}: {median['pymunk'] * 1e6:7.1f} us/team-step  ({CONFIG.physics_substeps} sub-steps)"
    )
    speedup, workers = ratio("team", "batched"), ratio("batched", "workers")
    rate = n / median["workers"]
    verdict = "met" if speedup >= 2.5 else "NOT met"
    print(f"  ratio batched / team by team, one core  : {speedup:.2f}x  (target >= 2.5x: {verdict})")
    print(f"  ratio 2 processes / one (batched)       : {workers:.2f}x")
    print(f"  ratio batched team-step / bare Pymunk   : {ratio('batched', 'pymunk'):.1f}x")
    print(f"  2 processes: {rate:,.0f} agent-steps/s (target >= 150,000: {'met' if rate >= 150_000 else 'NOT met'})")
    print("Agents pressed on walls, obstacles and each other (each holds one random action), batched, one core:")
    print(f"  contacts from Pymunk's arbiters         : {median['pressed'] * 1e6:7.1f} us/team-step")
    print(
        f"  plus a Python callback per contact      : {median['callbacks'] * 1e6:7.1f} us/team-step  "
        f"({ratio('callbacks', 'pressed'):.2f}x; a callback per contact instead of the arbiters)"
    )
    if args.reference:
        compare_with_reference(args, {label: median[name] for name, label in labels.items()})


def compare_with_reference(args: argparse.Namespace, seconds: dict[str, float]) -> None:
    """Run the reference commit's own benchmark with the same arguments and print the ratios of the rows both have."""
    with reference_checkout(args.reference) as tree:
        command = [sys.executable, str(tree / "benchmarks" / "env_throughput.py")]
        command += ["--steps", str(args.steps), "--repeats", str(args.repeats), "--teams", str(args.teams)]
        environment = {**os.environ, "PYTHONPATH": str(tree / "src")}
        output = subprocess.run(command, env=environment, check=True, capture_output=True, text=True).stdout
    print(f"Reference {args.reference}, its own benchmark, run right after:")
    print("".join(f"  | {line}\n" for line in output.splitlines()), end="")
    reference = {m[1].strip(): float(m[2]) * 1e-6 for m in re.finditer(r"^\s+(.+?):\s+([\d.]+) us/team-step", output, re.M)}
    print("This checkout's agent-steps/s against the reference's (same rows):")
    for label, value in seconds.items():
        if label in reference:
            print(f"  {label:36s}: {reference[label] / value:.2f}x")


if __name__ == "__main__":
    main()
