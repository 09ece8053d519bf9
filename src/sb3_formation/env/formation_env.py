"""``FormationEnv``: one team of agents as a PettingZoo ``ParallelEnv``, a view of one team of a
:class:`~sb3_formation.env.engine.FormationEngine`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, NoReturn, cast

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.geometry import reference_bearings, ring_neighbours
from sb3_formation.env.observations import ObservationField, observation_layout
from sb3_formation.env.rendering import HumanWindow, render_frame
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.sensors import Lidar
from sb3_formation.env.state import TeamState, state_fields, state_layout, state_vector
from sb3_formation.env.world import World

AgentID = str


class FormationEnv(ParallelEnv):  # type: ignore[misc]  # pettingzoo ships no type information: ParallelEnv is Any
    """A team of n agents (holonomic second-order points, or unicycles) that must bring its centroid to a goal, in
    formation, around obstacles.

    Thesis: chapters 3-5; every interpretation is pinned in ``docs/design.md``. Agents are ``"agent_0"`` ...
    ``"agent_{n-1}"``; agent_0 is the thesis's agent 1. Agent i's designated neighbours are agents i - 1 and i + 1
    (mod n); the reference shape is the regular n-gon traversed anti-clockwise 0 -> 1 -> ... -> n-1.

    ## Action Space

    ``Box(-1, 1, (2,), float32)`` per agent: the force (F_x, F_y) as a fraction of F_max (N), eq. 19. For unicycles
    (``dynamics="unicycle"``): the forward force along the heading as a fraction of F_max, and the turn rate as a
    fraction of ``max_turn_rate`` (rad/s) (:mod:`~sb3_formation.env.world`). Actions outside [-1, 1] are clipped; NaN,
    infinite or wrongly shaped actions raise ``ValueError``.

    ## Observation Space

    ``Box(low, high, (211,), float32)`` per agent for 90 lidar rays (thesis Table 3.1). Raw values; bounds are
    honest (every reachable value lies inside). ``env.observation_layout`` maps each field to its slice.

    | index     | field                          | meaning (Table 3.1)                                      | unit  |
    |-----------|--------------------------------|----------------------------------------------------------|-------|
    | 0-89      | lidar_obstacles                | l: obstacles and walls, distance / range, 1 = nothing    | -     |
    | 90-179    | lidar_agents                   | l: agents except self and neighbours, as above           | -     |
    | 180-181   | velocity                       | v^i                                                      | m/s   |
    | 182-185   | neighbour_offsets              | d_j^iv = p^j - p^i, preceding (x, y) then succeeding     | m     |
    | 186-189   | neighbour_relative_velocities  | v^j - v^i, preceding then succeeding                     | m/s   |
    | 190-191   | goal_offset                    | d_g^iv = p^g - p^i                                       | m     |
    | 192-193   | centroid_goal_offset           | c_g^v = p^g - p^c                                        | m     |
    | 194-195   | centroid_goal_offset_change    | c_g,t^v - c_g,t-1^v (0 after reset)                      | m     |
    | 196-197   | neighbour_distances            | d_j^i                                                    | m     |
    | 198       | centroid_distance              | d_c^i                                                    | m     |
    | 199-200   | neighbour_distance_errors      | d_j^i - d^ref                                            | m     |
    | 201       | centroid_distance_error        | eta_c - d_c^i                                            | m     |
    | 202       | angle_error                    | beta^ref - beta^i                                        | deg   |
    | 203-204   | neighbour_angle_errors         | beta^ref - beta^j of the preceding, succeeding neighbour | deg   |
    | 205       | flag_orientation               | 1 if beta^i in (0, 180)                                  | 0/1   |
    | 206       | flag_range                     | 1 if every agent is within d^ref of its neighbours       | 0/1   |
    | 207       | time_step                      | t                                                        | steps |
    | 208-209   | previous_action                | a_t-1^i (0 after reset)                                  | -     |
    | 210       | previous_reward                | r_t-1^i (0 after reset)                                  | -     |

    With ``observe_reference_bearings`` (a departure from Table 3.1, for policies acting in teams of several sizes)
    four values follow: ``reference_bearings``, the unit reference bearings g_j^{i,ref} (Table 5.2) towards the
    preceding (x, y) then succeeding neighbour, which depend on the agent's index and on n. A unicycle's observation
    (an extension of Table 3.1) has two more values before those: ``heading``, (cos theta^i, sin theta^i) of its
    heading in the world frame; its other fields stay in the world frame, and its velocity is along the heading.

    ## Rewards

    Per agent, the weighted sum of the terms below (coefficients: ``FormationConfig``, tasks from Tables 4.1 and
    5.1), terms of the stage's ``stage_disabled_terms`` left out, clipped to [-10, 10]. ``infos[agent]["reward_<term>"]``
    holds every term before its coefficient (flat keys, :data:`~sb3_formation.env.config.REWARD_INFO_KEYS`). With
    ``team_reward`` each per-agent term is replaced by its team average and ``coll`` by the team collision term
    (eqs 27-32).

    | term     | equation  | value                                                                          |
    |----------|-----------|--------------------------------------------------------------------------------|
    | time     | 33        | r_late on the step that reaches T_s, else 0                                    |
    | angle    | 21, 34    | -abs(beta^ref - beta^i) / m_ang                                                |
    | bearing  | 35        | -0.5 * mean over the two neighbours of norm(g_ref - g)                         |
    | dist     | 22, 36    | -mean over neighbours of max(d_j - d^ref, 0) / m_dist                          |
    | centroid | 37        | r_c if d_c^i <= eta_c, else 0                                                  |
    | goal     | 23, 38    | r_reached if the centroid is within eta_g of the goal, else k_1 + progress / (dt v_max) |
    | move     | 25, 40    | -angle between v_t^i and v_t+1^i (rad; 0 if either is still)                   |
    | velocity | 41        | -mean over neighbours of the angle between v_t+1^i and v_t^j (rad)             |
    | coll     | 24, 39    | r_j if any agent is within 2 R_a, else r_o if an obstacle or wall is closer than d_safe, else 0 |

    ## Episode End

    Termination: the centroid is within eta_g of the goal (every agent gets r_reached). Truncation: ``max_steps``
    (T_s) steps. Contacts never end an episode. After either, ``env.agents`` is empty until ``reset``.

    ## Info

    After reset and after every step, ``infos[agent]`` has ``angle_error_deg`` (abs), ``bearing_error`` (mean over the
    two neighbours of norm(g_ref - g)), ``neighbour_distance_error`` (m, mean positive part), ``centroid_distance`` (m,
    agent to centroid), ``goal_distance`` (m, centroid to goal), ``collisions_obstacle`` and ``collisions_agent``
    (obstacles or walls, and other agents, touched during this step; a pair is counted once per step),
    ``collisions_rammed`` (of the obstacle contacts, the moving obstacles that ran into the agent while it commanded no
    velocity towards them: 0 where nothing moves), ``success`` and ``reward_<term>`` for every term below. Contacts
    are Pymunk's, over the step's sub-steps; the collision reward reads the distances at the end of the step (eqs
    24/39), so a touch that has already ended by then is counted but not penalised.

    ## Reset options

    ``options={"scenario": Scenario(...)}`` places everything by hand (validated against the config); otherwise the
    scenario of the current curriculum stage is drawn from the env's own generator. Other keys are ignored, as
    Gymnasium environments do.

    ## The engine behind it

    The env keeps no episode state of its own: it is a view of one team of a
    :class:`~sb3_formation.env.engine.FormationEngine` (by default an engine of this one team), which resets and steps
    it. A ``FormationVecEnv`` holds one such view per team of its engines, for ``get_attr`` and ``env_method``; those
    views are stepped by the VecEnv, not through ``step``.

    :param config: task configuration; default ``FormationConfig()``
    :param render_mode: ``None``, ``"rgb_array"`` or ``"human"`` (a window; needs the ``human`` extra, pygame)
    :param render_lidar: draw the lidar rays in renderings
    :param engine: the engine whose team this env shows (default: a new engine of one team of ``config``)
    :param team: the team of ``engine``
    """

    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": ["human", "rgb_array"],
        "name": "formation_v0",
        "render_fps": 20,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: FormationConfig | None = None,
        render_mode: str | None = None,
        render_lidar: bool = False,
        *,
        engine: FormationEngine | None = None,
        team: int = 0,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            modes = self.metadata["render_modes"]
            raise ValueError(f"render_mode={render_mode!r} is not supported; use one of {modes} or None")
        if engine is None:
            engine = FormationEngine([config if config is not None else FormationConfig()])
        elif config is not None and config != engine.configs[team]:
            raise ValueError(f"config differs from team {team}'s of the engine; give one or the other")
        self.engine, self.team = engine, team
        self.config = config = engine.configs[team]
        self.render_mode = render_mode
        self.render_lidar = render_lidar
        self.possible_agents: list[AgentID] = [f"agent_{index}" for index in range(config.n_agents)]
        fields: (
            list[ObservationField] | list[tuple[str, int, np.ndarray, np.ndarray, str]]
        )  # the observation's, then the state's
        fields = engine.observation_fields
        self.observation_layout: dict[str, slice] = observation_layout(fields)
        low = np.concatenate([field.low for field in fields]).astype(np.float32)
        high = np.concatenate([field.high for field in fields]).astype(np.float32)
        observation_space = gymnasium.spaces.Box(low, high, dtype=np.float32)
        action_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.observation_spaces = dict.fromkeys(self.possible_agents, observation_space)
        self.action_spaces = dict.fromkeys(self.possible_agents, action_space)
        #: True for the 0/1 flag entries of the observation (left alone by normalisation)
        self.binary_observation_mask = np.concatenate([np.full(field.size, field.binary) for field in fields])
        self.neighbours = ring_neighbours(config.n_agents)
        self.reference_bearings = reference_bearings(config.n_agents)
        fields = state_fields(config)
        #: PettingZoo's global state space: the fields of :func:`~sb3_formation.env.state.state_fields`, in order
        self.state_space = gymnasium.spaces.Box(
            np.concatenate([low for _, _, low, _, _ in fields]).astype(np.float32),
            np.concatenate([high for _, _, _, high, _ in fields]).astype(np.float32),
            dtype=np.float32,
        )
        #: field name -> slice of ``state()``
        self.state_layout: dict[str, slice] = state_layout(config)
        self._rows = engine.team_rows(team)
        self._renderer: Any = None

    def observation_space(self, agent: AgentID) -> gymnasium.spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: AgentID) -> gymnasium.spaces.Box:
        return self.action_spaces[agent]

    # The team's state, as the engine holds it ---------------------------------------------------------------------

    @property
    def agents(self) -> list[AgentID]:
        """The live agents: all of them during an episode, none after it ended (or before the first reset)."""
        return list(self.possible_agents) if self.engine.live[self.team] else []

    @property
    def stage(self) -> int:
        """The curriculum stage (1, 2 or 3); setting it is :meth:`set_stage`."""
        return int(self.engine.stages[self.team])

    @stage.setter
    def stage(self, stage: int) -> None:
        self.set_stage(stage)

    def set_stage(self, stage: int) -> None:
        """Switch the curriculum stage (1, 2 or 3); takes effect for rewards at once and for placements at the next reset."""
        self.engine.set_stage(self.team, stage)

    @property
    def np_random(self) -> np.random.Generator:
        """The team's scenario generator."""
        return self.engine.generators[self.team]

    @np_random.setter
    def np_random(self, generator: np.random.Generator) -> None:
        self.engine.generators[self.team] = generator

    @property
    def np_random_seed(self) -> int:
        return self.engine.generator_seeds[self.team]

    @property
    def scenario(self) -> Scenario | None:
        """The episode's placements (``None`` before the first reset)."""
        return self.engine.scenarios[self.team]

    @property
    def world(self) -> World | None:
        """The team's Pymunk world (``None`` before the first reset)."""
        return self.engine.worlds[self.team]

    @property
    def lidar(self) -> Lidar:
        """The team's lidar, with the episode's obstacles."""
        return self.engine.lidars[self.team]

    @property
    def goal(self) -> np.ndarray:
        goal: np.ndarray = self.engine.episodes.goals[self.team].copy()
        return goal

    @property
    def obstacles(self) -> np.ndarray:
        """``(m, 3)`` obstacle x, y, radius (m) of the episode."""
        return np.zeros((0, 3)) if self.scenario is None else cast(np.ndarray, self.scenario.obstacles)  # an array once built

    @property
    def walls(self) -> np.ndarray:
        """``(w, 5)`` walls x0, y0, x1, y1, thickness (m) of the episode (:mod:`~sb3_formation.env.shapes`)."""
        return np.zeros((0, 5)) if self.scenario is None else cast(np.ndarray, self.scenario.walls)  # an array once built

    @property
    def step_count(self) -> int:
        """Steps played since the last reset."""
        return int(self.engine.episodes.step_counts[self.team])

    # Episode ------------------------------------------------------------------------------------------------------

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[AgentID, np.ndarray], dict[AgentID, dict[str, Any]]]:
        scenario = (options or {}).get("scenario")
        if scenario is not None and not isinstance(scenario, Scenario):
            raise TypeError(f"options['scenario'] must be a Scenario, got {type(scenario).__name__}")
        observations = self.engine.reset(self.team, seed=seed, scenario=scenario)
        return dict(zip(self.possible_agents, observations)), dict(zip(self.possible_agents, self.engine.infos(self.team)))

    def step(
        self, actions: dict[AgentID, np.ndarray]
    ) -> tuple[
        dict[AgentID, np.ndarray],
        dict[AgentID, float],
        dict[AgentID, bool],
        dict[AgentID, bool],
        dict[AgentID, dict[str, Any]],
    ]:
        if not self.agents:
            raise RuntimeError("step() called on a finished episode (or before reset()); call reset() first")
        if not isinstance(actions, Mapping):
            raise TypeError(
                f"step() takes a dict of one action per agent (PettingZoo's parallel API), got {type(actions).__name__}; "
                "step_array() takes an (n, 2) array"
            )
        agents = self.agents
        observations, rewards, terminated, truncated, infos = self._advance(self._action_array(actions))
        return (
            dict(zip(agents, observations)),
            dict(zip(agents, rewards.tolist())),
            dict.fromkeys(agents, terminated),
            dict.fromkeys(agents, truncated),
            dict(zip(agents, infos)),
        )

    def step_array(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool, bool, list[dict[str, Any]]]:
        """:meth:`step` with arrays in agent order.

        :param actions: ``(n, 2)`` actions, row i for agent i (clipped to [-1, 1]; NaN or infinite values raise)
        :return: observations ``(n, dim)``, rewards ``(n,)``, terminated, truncated, and the agents' infos in order
        """
        if not self.agents:
            raise RuntimeError("step_array() called on a finished episode (or before reset()); call reset() first")
        actions = real_actions(actions, "actions")
        if actions.shape != (len(self.possible_agents), 2):
            raise ValueError(f"actions must have shape ({len(self.possible_agents)}, 2), got {actions.shape}")
        finite = np.isfinite(actions).all(axis=1)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise ValueError(f"action of {self.possible_agents[bad]} is not finite: {actions[bad].tolist()}")
        return self._advance(np.minimum(np.maximum(actions, -1.0), 1.0))

    def _advance(self, clipped: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool, bool, list[dict[str, Any]]]:
        """One step of the team under validated, clipped ``(n, 2)`` actions."""
        engine = self.engine
        if engine.n_teams > 1:
            raise RuntimeError(
                f"this env is team {self.team} of an engine of {engine.n_teams} teams, which steps them together "
                "(a FormationVecEnv's): step that, or make a FormationEnv of its own"
            )
        step = engine.step(clipped)
        team = self.team
        return (
            step.observations,  # the engine never writes an array it returned
            step.rewards,
            bool(step.terminated[team]),
            bool(step.truncated[team]),
            engine.infos(team),
        )

    # Internals ----------------------------------------------------------------------------------------------------

    def _action_array(self, actions: dict[AgentID, np.ndarray]) -> np.ndarray:
        """Validate the action of every agent and return them clipped to [-1, 1] as an ``(n, 2)`` array."""
        try:
            array = real_actions([actions[agent] for agent in self.agents], "actions")
        except (KeyError, ValueError, TypeError):
            array = None
        if array is None or array.shape != (len(self.agents), 2) or len(actions) != len(self.agents):
            self._raise_for_actions(actions)
        if not np.isfinite(array).all():
            bad = self.agents[int(np.flatnonzero(~np.isfinite(array).all(axis=1))[0])]
            raise ValueError(f"action of {bad} is not finite: {np.asarray(actions[bad]).tolist()}")
        clipped: np.ndarray = np.minimum(np.maximum(array, -1.0), 1.0)
        return clipped

    def _raise_for_actions(self, actions: dict[AgentID, np.ndarray]) -> NoReturn:
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise ValueError(f"no action given for {missing}")
        unknown = [agent for agent in actions if agent not in self.agents]
        if unknown:
            raise ValueError(f"actions given for agents that are not live: {unknown}; live agents are {self.agents}")
        for agent in self.agents:
            try:
                action = real_actions(actions[agent], f"action of {agent}")
            except (ValueError, TypeError) as error:
                raise ValueError(f"action of {agent} is not real numbers: {actions[agent]!r}") from error
            if action.shape != (2,):
                raise ValueError(f"action of {agent} must have shape (2,), got {action.shape}")
        raise ValueError(f"actions could not be read as one (2,) array per agent: {actions!r}")

    # State --------------------------------------------------------------------------------------------------------

    def team_state(self) -> TeamState:
        """A frozen snapshot of the team now (after the last reset or step): positions, velocities, goal, obstacles,
        neighbour graph, lidar readings, contacts of the last step, formation errors and the step count."""
        if self.world is None:
            raise RuntimeError("team_state() called before reset()")
        return self.engine.team_state(self.team)

    def episode_summary(self) -> dict[str, Any]:
        """The episode so far: means over its steps of the formation errors and reward terms, collision totals,
        success and stage (:func:`~sb3_formation.env.episodes.episode_summary`)."""
        return self.engine.episode_summary(self.team)

    def state(self) -> np.ndarray:
        """PettingZoo's global state: a flat float32 vector laid out as ``self.state_layout`` (see
        :func:`~sb3_formation.env.state.state_fields`: positions, velocities, goal, obstacles, step)."""
        return state_vector(self.team_state(), self.config)

    # Rendering ----------------------------------------------------------------------------------------------------

    def render(self, mode: str | None = None) -> np.ndarray | None:
        """``rgb_array``: an ``(H, W, 3)`` uint8 image of the world; ``human``: draw it in a window.

        :param mode: the render mode, default ``render_mode``; older wrappers (RLlib's ``ParallelPettingZooEnv``) pass
            it as an argument, as the PettingZoo API once did
        """
        mode = self.render_mode if mode is None else mode
        if mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        if mode not in self.metadata["render_modes"]:
            raise ValueError(f"render mode {mode!r} is not supported; use one of {self.metadata['render_modes']}")
        if self.world is None:
            raise RuntimeError("render() called before reset()")
        frame = render_frame(self.team_state(), self.config, draw_lidar=self.render_lidar)
        if mode == "rgb_array":
            return frame
        if self._renderer is None:
            self._renderer = HumanWindow(frame.shape[1], frame.shape[0], self.metadata["render_fps"])
        self._renderer.show(frame)
        return None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def real_actions(values: Any, what: str) -> np.ndarray:
    """``values`` as a float64 array.

    :param what: what they are, for the message
    :raises ValueError: rows of different lengths, or values that are not real numbers (complex ones too: numpy would
        drop their imaginary parts with a mere warning)
    """
    array = np.asarray(values)  # numpy refuses ragged rows with a ValueError
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{what} must be real numbers, got {array.dtype} values")
    return array.astype(np.float64)
