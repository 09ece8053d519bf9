"""A fast recipe against its thesis recipe on the same small agent-step budget, seed and evaluation episodes.

The thesis recipe keeps its curriculum's proportions (20 / 20 / 60 % of the iterations in stages 1 / 2 / 3, as
5000 : 5000 : 15000 in thesis 5.3); with ``--thesis-mlp`` it runs the chapter-4 MLP policy instead of the recurrent
one of figs 5.1-5.2, which costs about 4x per step. Both final models play the same stage-3 episodes (seed 0 onwards,
deterministic actions). It prints each recipe's stage plan, training wall time and success rate.

    python benchmarks/fast_vs_thesis.py --fast fast-ch5-bearing --thesis ch5-bearing --steps 800000 --teams 8 --thesis-mlp
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from sb3_formation.cli.common import assignment
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.runs import load_trained
from sb3_formation.experiment.settings import layered_settings
from sb3_formation.experiment.training import train


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
    args = parser.parse_args()
    budget = {"steps": args.steps, "n_envs": args.teams, "seed": args.seed, "progress_bar": False, "env": dict(args.env)}
    fast = layered_settings(recipe=args.fast, logdir=str(args.logdir), **budget)
    thesis = layered_settings(recipe=args.thesis, recurrent=False if args.thesis_mlp else None, logdir=str(args.logdir),
                           **budget)  # fmt: skip
    for settings in (fast, thesis):
        started = time.perf_counter()
        run = train(settings, command=f"benchmarks/fast_vs_thesis.py {settings.recipe.name}")
        seconds = time.perf_counter() - started
        summary = evaluate(load_trained(run), episodes=args.episodes, stage=3, seed=0).summary
        print(f"{settings.recipe.name}: stages {list(settings.recipe.stage_iterations())}, trained {seconds / 60:.1f} min, "
              f"success {summary['success_rate']:.1%} of {args.episodes}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
