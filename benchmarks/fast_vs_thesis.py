"""A fast recipe against its thesis recipe on the same small agent-step budget, seed and evaluation episodes.

The thesis recipe keeps its curriculum's proportions (20 / 20 / 60 % of the iterations in stages 1 / 2 / 3, as
5000 : 5000 : 15000 in thesis 5.3); with ``--thesis-mlp`` it runs the chapter-4 MLP policy instead of the recurrent
one of figs 5.1-5.2, which costs about 4x per step. Both final models play the same stage-3 episodes (seed 0 onwards,
deterministic actions). It prints each recipe's stage plan, training wall time and success rate.

    python benchmarks/fast_vs_thesis.py --fast fast-ch5-bearing --thesis ch5-bearing --steps 800000 --teams 8 --thesis-mlp

``--small-world`` is the comparison the test suite ran until it moved here (it took about 12 minutes of the suite):
the chapter-5 bearing task with 3 agents, v_max 0.2 m/s and 400-step episodes, 600,000 agent-steps of each recipe on 8
teams, the thesis recipe with the MLP policy, torch on one thread, 40 episodes; it also says whether the fast recipe's
success rate is at least 20 points above the thesis recipe's, the margin the test asserted.

    python benchmarks/fast_vs_thesis.py --small-world
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from sb3_formation.cli.common import assignment
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import layered_settings
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.training import train
from sb3_formation.utils.machine import machine_line

#: The world of ``--small-world``: the chapter-5 bearing task (Table 5.1) with 3 agents, four times the thesis's v_max
#: (6 cm per step, 3 cm per sub-step < R_a) and 400-step episodes.
SMALL_WORLD = {"n_agents": 3, "v_max": 0.2, "max_steps": 400}
#: Points of success rate by which the fast recipe is expected to beat the thesis recipe with ``--small-world``.
SMALL_WORLD_MARGIN = 0.2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fast", default="fast-ch5-bearing", help="the fast recipe")
    parser.add_argument("--thesis", default="ch5-bearing", help="the thesis recipe")
    parser.add_argument("--steps", type=int, default=800_000, help="agent-step budget of each recipe")
    parser.add_argument("--teams", type=int, default=8, help="teams of both recipes")
    parser.add_argument("--seed", type=int, default=0, help="training seed of both recipes")
    parser.add_argument("--episodes", type=int, default=40, help="stage-3 evaluation episodes (seed 0 onwards)")
    parser.add_argument("--env", type=assignment, action="append", default=[], metavar="FIELD=VALUE",
                        help="a FormationConfig override for both recipes, e.g. n_agents=3 (repeatable)")  # fmt: skip
    parser.add_argument("--thesis-mlp", action="store_true", help="the thesis recipe with the MLP policy")
    parser.add_argument("--logdir", type=Path, default=Path("runs/benchmark-fast-vs-thesis"), help="folder of the runs")
    parser.add_argument("--small-world", action="store_true",
                        help="the small-world comparison: 3 agents, v_max 0.2, 400-step episodes, 600,000 agent-steps, "
                             "8 teams, the thesis recipe with the MLP policy, one torch thread")  # fmt: skip
    args = parser.parse_args()
    print(f"fast_vs_thesis, {machine_line()}", flush=True)
    if args.small_world:
        args.env = [*SMALL_WORLD.items(), *args.env]
        args.steps, args.teams, args.thesis_mlp = 600_000, 8, True
        torch.set_num_threads(1)
    budget = {"steps": args.steps, "n_envs": args.teams, "seed": args.seed, "progress_bar": False, "env": dict(args.env)}
    fast = layered_settings(recipe=args.fast, logdir=str(args.logdir), **budget)
    thesis = layered_settings(recipe=args.thesis, recurrent=False if args.thesis_mlp else None, logdir=str(args.logdir),
                           **budget)  # fmt: skip
    rates = []
    for settings in (fast, thesis):
        started = time.perf_counter()
        run = train(settings, command=f"benchmarks/fast_vs_thesis.py {settings.recipe.name}")
        seconds = time.perf_counter() - started
        summary = evaluate(load_trained(run), episodes=args.episodes, stage=3, seed=0).summary
        rates.append(summary["success_rate"])
        print(f"{settings.recipe.name}: stages {list(settings.recipe.stage_iterations())}, trained {seconds / 60:.1f} min, "
              f"success {summary['success_rate']:.1%} of {args.episodes}", flush=True)  # fmt: skip
    margin = rates[0] - rates[1]
    print(f"fast minus thesis: {margin * 100:+.1f} points of success", flush=True)
    if args.small_world:
        met = "met" if margin >= SMALL_WORLD_MARGIN else "NOT met"
        print(f"expected margin >= {SMALL_WORLD_MARGIN * 100:.0f} points: {met}", flush=True)


if __name__ == "__main__":
    main()
