"""Environment throughput: agent-steps per second of ``FormationEnv`` against the bare Pymunk step, in one run.

Random actions, curriculum stage 3, n = 6 (ch5-bearing), 90-ray lidar on. Prints medians over repeats:
- one env on one core (the issue's target: >= 40,000 agent-steps/s);
- a batch of envs stepped in one process, and the same batch split over two worker processes (both cores);
- the bare Pymunk ``space.step`` of the same team (sub-steps included), so our overhead is a printed ratio.

Usage: ``python benchmarks/env_throughput.py [--steps 3000] [--repeats 5] [--batch 8]``
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time

import numpy as np

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.world import World

CONFIG = FormationConfig.preset("ch5-bearing", stage=3)


def _actions(env: FormationEnv, steps: int, seed: int) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [{agent: rng.uniform(-1.0, 1.0, 2) for agent in env.possible_agents} for _ in range(steps)]


def env_seconds_per_step(n_envs: int, steps: int, seed: int = 0, barrier: object | None = None) -> float:
    """Wall time (s) per team-step of ``n_envs`` envs stepped in turn with pre-drawn random actions.

    :param barrier: a ``multiprocessing.Barrier`` to wait on after warming up, so that parallel workers time together
    """
    envs = [FormationEnv(CONFIG) for _ in range(n_envs)]
    for index, env in enumerate(envs):
        env.reset(seed=seed + index)
    actions = _actions(envs[0], steps, seed)
    envs[0].step(actions[0])  # compile the numba kernels outside the timed loop
    if barrier is not None:
        barrier.wait()
    start = time.perf_counter()
    for action in actions:
        for env in envs:
            env.step(action)
            if not env.agents:
                env.reset()
    return (time.perf_counter() - start) / (steps * n_envs)


def pymunk_seconds_per_step(steps: int, seed: int = 0) -> float:
    """Wall time (s) of Pymunk's own ``space.step`` calls for one team-step (all sub-steps), agents moving at random."""
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


def _worker(n_envs: int, steps: int, seed: int, barrier: object, results: multiprocessing.Queue) -> None:
    results.put(env_seconds_per_step(n_envs, steps, seed, barrier))


def parallel_seconds_per_step(n_envs: int, steps: int, workers: int) -> float:
    """Wall time per team-step with ``n_envs`` envs split evenly over ``workers`` processes timed together."""
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(workers), context.Queue()
    per_worker = n_envs // workers
    processes = [
        context.Process(target=_worker, args=(per_worker, steps, 100 * index, barrier, results)) for index in range(workers)
    ]
    for process in processes:
        process.start()
    per_step = [results.get() for _ in processes]
    for process in processes:
        process.join()
    slowest = max(per_step) * per_worker  # seconds for one step of a worker's whole batch
    return slowest / (per_worker * workers)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args()
    n_agents = CONFIG.n_agents

    # one env and the bare Pymunk step are measured back to back in every repeat, so each ratio sees the same machine
    singles, bares = [], []
    for seed in range(args.repeats):
        singles.append(env_seconds_per_step(1, args.steps, seed))
        bares.append(pymunk_seconds_per_step(args.steps, seed))
    single, bare = statistics.median(singles), statistics.median(bares)
    ratio = statistics.median(one / other for one, other in zip(singles, bares))
    batch = statistics.median(
        env_seconds_per_step(args.batch, args.steps // args.batch * 2, seed) for seed in range(args.repeats)
    )
    parallel = statistics.median(
        parallel_seconds_per_step(args.batch, args.steps // args.batch * 2, workers=2) for _ in range(args.repeats)
    )

    print(f"FormationEnv throughput, ch5-bearing stage 3, n = {n_agents}, {CONFIG.lidar_rays}-ray lidar, random actions")
    print(f"medians of {args.repeats} repeats of {args.steps} steps")
    print(f"  one env, one core           : {single * 1e6:8.1f} us/team-step  {n_agents / single:10,.0f} agent-steps/s")
    print(
        f"  {args.batch} envs, one core           : {batch * 1e6:8.1f} us/team-step  {n_agents / batch:10,.0f} agent-steps/s"
    )
    rate = n_agents / parallel
    print(f"  {args.batch} envs, 2 worker processes : {parallel * 1e6:8.1f} us/team-step  {rate:10,.0f} agent-steps/s")
    print(f"  bare Pymunk space.step      : {bare * 1e6:8.1f} us/team-step  ({CONFIG.physics_substeps} sub-steps)")
    print(f"  ratio env step / bare Pymunk step (median of per-repeat ratios): {ratio:.1f}x")
    print(f"  ratio 2 workers / one core ({args.batch} envs): {batch / parallel:.2f}x")
    print(f"  target >= 40,000 agent-steps/s on one core: {'met' if n_agents / single >= 40_000 else 'NOT met'}")


if __name__ == "__main__":
    main()
