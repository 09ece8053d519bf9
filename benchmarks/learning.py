"""Learning benchmark: train recipes for a budget on several seeds, evaluate each on the thesis protocol, print tables.

For every recipe and seed (one after the other, each on the whole machine) it trains ``--steps`` agent-steps (or
``--minutes`` of wall-clock) with periodic evaluation every ``--eval-every`` iterations (20 stage-3 episodes from seed
1,000,000), then evaluates the final model on the thesis's protocol (``--episodes`` stage-3 episodes from seed 0,
deterministic actions). It prints:

- a Markdown table: the thesis's published results, then one row per recipe and seed (success with its 95 % Wilson
  interval; over successful episodes the angle, bearing and distance errors, agent and obstacle contacts and steps to
  the goal; wall time; agent-steps per second);
- time to success: wall-clock and agent-steps until the periodic evaluation first reached 50 %, 80 % and 90 %;
- a figure of the periodic success rate against wall-clock, per recipe and seed (``--out``).

``--controllers classical`` adds a row per controller and thesis task (``--controller-recipes``), evaluated on the
same protocol and seeds (its wall time is the evaluation's; it trains nothing).

A thesis recipe trained on the same budget keeps its curriculum's proportions (stages 1, 2 and 3 get 20, 20 and 60 %
of the budget's iterations, or of its minutes, as 5000 : 5000 : 15000 in thesis 5.3).

    python benchmarks/learning.py --recipes fast-ch5-bearing,ch5-bearing --seeds 0,1,2 --steps 6000000
    python benchmarks/learning.py --recipes fast-ch5-bearing,ch5-bearing --seeds 0,1,2 --minutes 15
    python benchmarks/learning.py --recipes "" --controllers classical
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_formation.experiment.evaluation import evaluate_target
from sb3_formation.experiment.recipes import layered_settings
from sb3_formation.experiment.reports import table_number
from sb3_formation.experiment.targets import Target
from sb3_formation.experiment.training import train
from sb3_formation.utils.machine import machine_line
from sb3_formation.viz.plots import save_figure

#: The thesis's published results (thesis 4.4 and 5.4): success rate; mean angle error around 30 deg.
THESIS_RESULTS = {"ch4-individual": 0.05, "ch4-team": 0.07, "ch5-angle": 0.08, "ch5-bearing": 0.11}
LEVELS = (0.5, 0.8, 0.9)
Budget = tuple[str, float]


def run(setup: str, seed: int, budget: Budget, eval_every: int, logdir: Path) -> tuple[Path, float]:
    """Train one recipe and seed for the budget; return the run folder and the training wall time (s).

    :param budget: ``("steps", agent-steps)`` or ``("minutes", minutes)``
    """
    kind, amount = budget  # a curriculum is spread over either budget in its proportions
    settings = layered_settings(
        recipe=setup, seed=seed, eval_every=eval_every, progress_bar=False, logdir=str(logdir), **{kind: amount}
    )
    run_dir = logdir / f"{Path(setup).stem}_s{seed}"  # a recipe file: its name without folder and suffix
    started = time.perf_counter()
    train(settings, command=f"benchmarks/learning.py {setup} seed {seed}", run_dir=run_dir)
    return run_dir, time.perf_counter() - started


def success_over_time(run_dir: Path) -> tuple[list[tuple[float, int, float]], int]:
    """(seconds since training started, agent-steps, success rate) of every periodic evaluation of a run, and the
    agent-steps the run trained."""
    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    scalars = [event for tag in events.Tags()["scalars"] for event in events.Scalars(tag)]
    start = min(event.wall_time for event in scalars)
    curve = [(event.wall_time - start, event.step, event.value) for event in events.Scalars("eval/success_rate")]
    return curve, max(event.step for event in scalars)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipes", default="fast-ch5-bearing", help="comma-separated recipes (may be empty)")
    parser.add_argument("--controllers", default="", help="comma-separated controllers to evaluate beside the recipes")
    parser.add_argument(
        "--controller-recipes", default=",".join(THESIS_RESULTS), help="comma-separated recipes the controllers act in"
    )
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    budgets = parser.add_mutually_exclusive_group()
    budgets.add_argument("--steps", type=int, default=6_000_000, help="training budget in agent-steps per run")
    budgets.add_argument("--minutes", type=float, help="training budget in minutes of wall-clock per run (not --steps)")
    parser.add_argument("--eval-every", type=int, default=25, help="iterations between periodic evaluations")
    parser.add_argument(
        "--episodes", type=int, help="final evaluation episodes (default: the recipe's protocol; thesis 4.4: 500, 5.4: 200)"
    )
    parser.add_argument("--logdir", type=Path, default=Path("runs/benchmark-learning"), help="folder of the runs")
    parser.add_argument("--out", type=Path, default=Path("learning.png"), help="success-against-time figure")
    args = parser.parse_args()
    print(f"learning benchmark, {machine_line()}", flush=True)
    budget = ("steps", args.steps) if args.minutes is None else ("minutes", args.minutes)
    rows, curves = [], {}
    protocol = {"episodes": args.episodes, "stage": 3, "seed": 0, "n_envs": 8}
    for setup in filter(None, args.recipes.split(",")):
        for seed in (int(seed) for seed in args.seeds.split(",")):
            run_dir, seconds = run(setup, seed, budget, args.eval_every, args.logdir)
            summary = evaluate_target(run_dir, changes=protocol, out=run_dir / "eval").summary
            curves[(setup, seed)], steps = success_over_time(run_dir)
            rows.append((setup, seed, summary, seconds, steps))
            print(f"{setup} seed {seed}: {summary['success_rate']:.1%} after {seconds / 60:.1f} min", flush=True)
    for name in filter(None, args.controllers.split(",")):
        for recipe in args.controller_recipes.split(","):
            started = time.perf_counter()
            out = args.logdir / f"controller-{name}_{Path(recipe).stem}"
            target = Target.parse(f"controller:{name}", recipe)
            summary = evaluate_target(target, changes=protocol, out=out).summary
            rows.append((f"controller:{name} on {recipe}", None, summary, time.perf_counter() - started, None))
            print(f"controller:{name} on {recipe}: {summary['success_rate']:.1%}", flush=True)
    print_tables(rows, curves, budget)
    if curves:
        draw(curves, args.out)


def print_tables(rows: list, curves: dict, budget: Budget) -> None:
    """The results table and the time-to-success table, in Markdown (controllers: no seed, no agent-steps)."""
    headings = ["recipe", "seed", "success (95 % CI)", "angle error (deg)", "bearing error", "distance error (m)",
                "agent contacts", "obstacle contacts", "steps to goal", "wall time (min)", "agent-steps/s"]  # fmt: skip
    episodes = sorted({summary["episodes"] for _, _, summary, _, _ in rows})
    print(f"\n{'/'.join(map(str, episodes))} stage-3 episodes (seed 0 onwards); means over the successful ones")
    kind, amount = budget
    print(f"budget {amount:,} {'agent-steps' if kind == 'steps' else 'minutes'} per run\n")
    print("| " + " | ".join(headings) + " |")
    print("|" + "|".join(["---", "---:"] + ["---:"] * (len(headings) - 2)) + "|")
    for name, rate in THESIS_RESULTS.items():
        print(f"| thesis {name} (published, 60-100 h) | - | {rate:.0%} | ~30 | - | - | - | - | - | 3600-6000 | - |")
    for setup, seed, summary, seconds, steps in rows:
        low, high = summary["success_rate_ci95"]
        means = summary["successful_episodes"]
        cells = [setup, "-" if seed is None else str(seed), f"{summary['success_rate']:.1%} ({low:.1%} - {high:.1%})"]
        for name in ("angle_error_deg", "bearing_error", "neighbour_distance_error", "collisions_agent",
                     "collisions_obstacle", "length"):  # fmt: skip
            cells.append("-" if means[name]["mean"] is None else table_number(means[name]["mean"]))
        cells += [f"{seconds / 60:.1f}", "-" if steps is None else f"{steps / seconds:,.0f}"]
        print("| " + " | ".join(cells) + " |")
    print("\nTime until the periodic evaluation (20 episodes) first reached a success rate\n")
    print("| recipe | seed | " + " | ".join(f"{level:.0%}: min / M agent-steps" for level in LEVELS) + " |")
    print("|---|---:|" + "---:|" * len(LEVELS))
    for (setup, seed), curve in curves.items():
        cells = []
        for level in LEVELS:
            reached = next(((seconds, steps) for seconds, steps, rate in curve if rate >= level), None)
            cells.append("not reached" if reached is None else f"{reached[0] / 60:.1f} / {reached[1] / 1e6:.2f}")
        print(f"| {setup} | {seed} | " + " | ".join(cells) + " |")


def draw(curves: dict, out: Path) -> None:
    """Periodic success rate against wall-clock minutes, one line per recipe and seed."""
    figure = Figure(figsize=(8.0, 4.5), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    for (setup, seed), curve in curves.items():
        axes.plot([seconds / 60 for seconds, _, _ in curve], [rate for _, _, rate in curve], label=f"{setup} seed {seed}")
    axes.set_xlabel("wall-clock (min)")
    axes.set_ylabel("success rate (20 stage-3 episodes)")
    axes.set_ylim(-0.02, 1.02)
    axes.legend(fontsize="small")
    print(f"\nfigure written to {save_figure(figure, out)}")


if __name__ == "__main__":
    main()
