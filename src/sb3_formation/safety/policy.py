"""Any policy behind the safety filter: :class:`SafePolicy`, a :class:`~sb3_formation.controllers.base.Policy` that
passes another one's actions through :class:`~sb3_formation.safety.filter.SafetyFilter` in both calls of the policy
contract, and keeps per-agent counts of what the filter did for the episode loop's rows. It is the one place where the
filter is applied to a policy (:class:`~sb3_formation.sb3.safety.SafetyVecEnv` applies it to a VecEnv for training)."""

from __future__ import annotations

from typing import Any

import numpy as np

from sb3_formation.controllers.base import AgentStep, Policy, TeamPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbed import MessageChannel
from sb3_formation.safety.filter import FilterBounds, FilterReport, SafetyFilter, SafetyGains, SentCommands

#: Keys of the per-episode safety metrics (:meth:`SafePolicy.episode_metrics`, evaluation rows, TensorBoard).
SAFETY_METRIC_KEYS = ("filter_changed_fraction", "filter_change_mean", "filter_infeasible_steps", "min_separation")


class FilterTally:
    """Running counts of a filter's reports, per row (agent slot): agent-steps, changed ones, the sum of the changes,
    infeasible ones, and the smallest separation (m)."""

    def __init__(self, rows: int = 0) -> None:
        self.resize(rows)

    def resize(self, rows: int) -> None:
        """Start counting ``rows`` rows afresh."""
        self.steps = np.zeros(rows, dtype=np.int64)
        self.changed = np.zeros(rows, dtype=np.int64)
        self.change = np.zeros(rows)
        self.infeasible = np.zeros(rows, dtype=np.int64)
        self.separation = np.full(rows, np.inf)

    def restart(self, rows: np.ndarray | slice) -> None:
        """Forget what ``rows`` counted (their episodes start)."""
        self.steps[rows] = self.changed[rows] = self.infeasible[rows] = 0
        self.change[rows] = 0.0
        self.separation[rows] = np.inf

    def add(self, report: FilterReport, rows: np.ndarray | slice = slice(None)) -> None:
        """Count one step of ``rows`` (default: every row), whose reports ``report`` holds in order."""
        self.steps[rows] += 1
        self.changed[rows] += report.changed
        self.change[rows] += report.change
        self.infeasible[rows] += report.infeasible
        self.separation[rows] = np.minimum(self.separation[rows], report.separation)

    def metrics(self, rows: np.ndarray | slice) -> dict[str, float]:
        """The metrics of :data:`SAFETY_METRIC_KEYS` over ``rows``: the share of their agent-steps the filter changed,
        the mean size of a change (fraction of F_max, over changed agent-steps; 0 if none), the infeasible agent-steps,
        and the smallest separation (m) the agents measured."""
        steps, changed = int(self.steps[rows].sum()), int(self.changed[rows].sum())
        return {
            "filter_changed_fraction": changed / max(steps, 1),
            "filter_change_mean": float(self.change[rows].sum()) / max(changed, 1),
            "filter_infeasible_steps": int(self.infeasible[rows].sum()),
            "min_separation": float(self.separation[rows].min()),
        }


class SafePolicy(Policy):
    """A policy whose actions pass through the safety filter; every other attribute is the wrapped policy's (so a
    privileged policy stays one, and ``seed`` reaches it). Wrapping a :class:`SafePolicy` filters once, with its gains
    unless others are given, and with its bounds unless others are given.

    :param policy: the policy that proposes actions
    :param gains: the filter's gains and margins (default :class:`SafetyGains`)
    :param bounds: the errors the filter stays safe under (default: those the task's disturbances declare,
        :meth:`FilterBounds.declared`, again for each task :meth:`fit` gives; a robot's own, e.g.
        ``FilterBounds.declared(load_disturbances("realistic"))``, are kept whatever the task)
    """

    policy: TeamPolicy
    filter: SafetyFilter

    def __init__(self, policy: TeamPolicy, gains: SafetyGains | None = None, bounds: FilterBounds | None = None) -> None:
        if isinstance(policy, SafePolicy):  # one filter is enough
            gains = gains or policy.filter.gains
            bounds = bounds if bounds is not None else getattr(policy, "bounds", None)
            policy = policy.policy
        self.policy = policy
        #: the task the wrapped policy acts in
        self.config: FormationConfig = policy.config
        #: the bounds given (``None``: the task's disturbances declare them)
        self.bounds = bounds
        self.filter = SafetyFilter(policy.config, gains, bounds)
        self.tally = FilterTally()
        #: the actions each row sent, for the filter's prediction over a declared delay
        self.sent = SentCommands(self.filter.bounds.horizon)
        #: what the filter did at the last :meth:`agent_step` (``None`` before the first)
        self.report: FilterReport | None = None

    def __getattr__(self, name: str) -> Any:
        # not yet set (unpickling): no recursion
        if name in ("policy", "config", "filter", "tally", "report", "sent", "bounds"):
            raise AttributeError(name)
        return getattr(self.policy, name)

    @property
    def message_size(self) -> int:
        return self.policy.message_size

    def fit(self, config: FormationConfig) -> SafePolicy:
        """The wrapped policy fitted to ``config`` behind a filter of the same gains, and of the bounds given, else of
        those ``config``'s disturbances declare (also where the wrapped policy fits as it is)."""
        fitted, given = self.policy.fit(config), getattr(self, "bounds", None)
        bounds = given if given is not None else FilterBounds.declared(config.disturbances)
        if fitted is self.policy and bounds == self.filter.bounds:
            return self
        safe = SafePolicy(fitted, self.filter.gains, bounds)
        safe.bounds = given  # bounds not given stay the task's: each fit declares them again
        return safe

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
        *,
        channel: MessageChannel | None = None,
        flying: np.ndarray | None = None,
    ) -> tuple[np.ndarray, Any]:
        """The wrapped policy's actions for raw team rows, filtered, and its next state; counts what the filter did
        (rows that start an episode start their counts afresh)."""
        told = {} if flying is None else {"flying": flying}  # a policy of a world without failures need not take it
        actions, state = self.policy.predict(observation, state, episode_start, deterministic, channel=channel, **told)
        rows = np.asarray(observation).reshape(-1, np.shape(observation)[-1])
        sent = self.sent.rows(len(rows), episode_start)
        safe, report = self.filter.filter(rows, np.asarray(actions).reshape(len(rows), 2), sent)
        self.sent.add(safe)
        if len(self.tally.steps) != len(rows):
            self.tally.resize(len(rows))
        elif episode_start is not None:
            self.tally.restart(np.asarray(episode_start, dtype=bool).reshape(-1))
        self.tally.add(report)
        return safe.reshape(np.shape(actions)), state

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """The wrapped policy's agent step with its actions filtered (its state and messages as they are); what the
        filter did is kept in :attr:`report`."""
        step = self.policy.agent_step(observations, agents, state, episode_start, received, deterministic)
        rows = np.asarray(observations).reshape(len(step.action), -1)
        safe, self.report = self.filter.filter(rows, step.action, self.sent.rows(len(rows), episode_start))
        self.sent.add(safe)
        return step._replace(action=safe)

    def episode_metrics(self, rows: slice) -> dict[str, float]:
        """What the filter did to ``rows`` (a team's) since their episode started (:meth:`FilterTally.metrics`)."""
        return self.tally.metrics(rows)


def with_filter(policy: TeamPolicy, filtered: bool) -> TeamPolicy:
    """``policy`` behind the safety filter or not: a :class:`SafePolicy` keeps its gains (an export trained behind the
    filter loads as one, with its own gains), any other policy gets the default gains; unfiltered, a
    :class:`SafePolicy` gives its wrapped policy.

    :param policy: the policy
    :param filtered: whether its actions pass through the filter
    """
    if filtered:
        return SafePolicy(policy)
    return policy.policy if isinstance(policy, SafePolicy) else policy
