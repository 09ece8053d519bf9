"""Evaluation summaries as Markdown tables (``sb3-formation compare``, ``sweep``, the result tables of the docs)."""

from __future__ import annotations

from typing import Any

from sb3_formation.sb3.metrics import EPISODE_METRICS

#: Columns of :func:`comparison_table` after the success rate.
TABLE_METRICS = {name: metric for name, metric in EPISODE_METRICS.items() if metric.in_table}


def comparison_table(summaries: dict[str, dict[str, Any]], over: str = "successful") -> str:
    """A Markdown table of evaluation summaries: success rate with its 95 % interval, then mean ± std of each metric.

    :param summaries: policy label -> :attr:`EvaluationResult.summary`
    :param over: ``"successful"`` (the thesis's choice) or ``"all"`` episodes for the means
    """
    if over not in ("successful", "all"):
        raise ValueError(f"over must be 'successful' or 'all', got {over!r}")
    headings = ["policy", "episodes", "success rate (95 % CI)", *(metric.label for metric in TABLE_METRICS.values())]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---"] + ["---:"] * (len(headings) - 1)) + "|"]
    for label, summary in summaries.items():
        low, high = summary["success_rate_ci95"]
        cells = [label, str(summary["episodes"]), f"{summary['success_rate']:.1%} ({low:.1%} - {high:.1%})"]
        for name in TABLE_METRICS:
            statistics = summary[f"{over}_episodes"][name]
            cells.append(
                "-"
                if statistics["mean"] is None
                else f"{table_number(statistics['mean'])} ± {table_number(statistics['std'])}"
            )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_number(value: float) -> str:
    """A table number: whole from 100, one decimal from 10, three significant digits below."""
    if abs(value) >= 100:
        return f"{value:.0f}"
    return f"{value:.1f}" if abs(value) >= 10 else f"{value:.3g}"
