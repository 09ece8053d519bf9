"""Start the simulator node or a team's agent nodes in one command, without ROS's own tools (``docs/deployment.md``).

``python -m sb3_formation.ros sim|agents MODEL.onnx ...`` runs the nodes (this module; it imports no torch);
``sb3-formation ros sim|agents TARGET ...`` names the policy as every other command does (``pretrained:ch5-bearing``)
and hands over to it. Options after ``--ros-args`` go to ROS (``--ros-args -p input_timeout:=2.0`` sets a parameter of
every node of the process).
"""

from __future__ import annotations

import argparse
import faulthandler
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sb3_formation.utils.arguments import MAX_EPISODES, OneLineParser, bounded_float, count, output_path, seed_value

#: ``--discovery`` choices -> ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (``localhost``: no traffic leaves the machine).
DISCOVERY_RANGES = {"localhost": "LOCALHOST", "subnet": "SUBNET", "off": "OFF", "system_default": "SYSTEM_DEFAULT"}
#: The agents' namespaces, ``{index}`` standing for an agent's index in its team.
AGENT_NAMESPACE = "agent_{index}"
#: (s) how long ``--process-per-agent`` waits for an agent's process to end after SIGTERM before it kills it (ROS 2's
#: ``ros2 launch`` waits 5 s; this leaves room for a loaded machine).
STOP_TIMEOUT = 10.0
#: The environment variable that tells an agent's process of ``--process-per-agent`` its parent's pid: the child ends
#: (SIGTERM to itself) when that parent dies, however it dies.
PARENT_VARIABLE = "SB3_FORMATION_ROS_PARENT"
#: Linux's ``prctl`` option that sends the calling process a signal when its parent dies.
PR_SET_PDEATHSIG = 1
#: ``--rate``: the free-running simulator's speed, from a thousandth of real time to a thousand times it.
MIN_RATE, MAX_RATE = 1e-3, 1e3
#: (s) ``--command-timeout`` at most a day.
MAX_COMMAND_TIMEOUT = 86_400.0


def add_arguments(commands: Any, model_help: str) -> None:
    """Add the ``sim`` and ``agents`` subcommands to ``commands`` (an argparse subparsers object).

    :param model_help: what the positional argument names (an ``.onnx`` file, or any target of ``sb3-formation``)
    """
    sim = commands.add_parser(
        "sim",
        help="the simulator as a ROS 2 node: scans, odometry, the goal and /clock out, Twist commands in",
        description="Fly a team of the package's engine over ROS 2 topics, episode k from reset(seed=SEED + k), as "
        "sb3-formation evaluate does. Synchronous mode steps when every agent's command of the step has arrived "
        "(deterministic); free mode steps at RATE times wall-clock speed with the latest commands.",
    )
    sim.add_argument("model", help=model_help + " (whose task the simulator flies)")
    sim.add_argument("--scenes", default="", help="the scenes to draw (default: the policy's)")
    sim.add_argument("--stage", type=int, default=3, help="curriculum stage 1-3 (default 3)")
    sim.add_argument("--seed", type=seed_value, default=0, help="episode k is played from reset(seed=SEED + k) (default 0)")
    sim.add_argument(
        "--episodes",
        type=count(MAX_EPISODES, minimum=0),
        default=1,
        help=f"episodes to play, then stop, at most {MAX_EPISODES:,} (default 1)",
    )
    sim.add_argument("--mode", choices=("sync", "free"), default="sync", help="synchronous (default) or free-running")
    sim.add_argument(
        "--rate",
        type=bounded_float(0.0, MAX_RATE),
        default=1.0,
        help=f"free mode: simulated seconds per wall-clock second, {MIN_RATE:g} to {MAX_RATE:g} (default 1)",
    )
    sim.add_argument(
        "--command-timeout",
        type=bounded_float(0.0, MAX_COMMAND_TIMEOUT),
        default=30.0,
        help=f"sync mode: wall-clock seconds to wait for a step's commands, at most {MAX_COMMAND_TIMEOUT:g} (default 30)",
    )
    sim.add_argument(
        "--see-through-agents",
        action="store_true",
        help="scans see through the agents, as the simulator's lidar does (a check of the nodes; default: agents stop beams)",
    )
    sim.add_argument(
        "--disturbances",
        default="ideal",
        metavar="NAME|FILE",
        help="the episodes' disturbances: a profile (ideal, realistic, harsh) or a YAML file; the scans and odometry "
        "carry the sensing errors, late as the observation delay says (default ideal)",
    )
    sim.add_argument(
        "--out", type=output_path, default=None, help="write every episode (seed, success, steps, positions) to this .npz"
    )
    _add_ros_options(sim)
    agents = commands.add_parser(
        "agents",
        help="a team's agent nodes: each runs the policy and the safety filter on its robot's scan, odometry and goal",
        description="One agent node per robot: LaserScan, every teammate's Odometry and the goal in, Twist out. All "
        "of a team's nodes in one process and executor, or one process per agent.",
    )
    agents.add_argument("model", help=model_help)
    agents.add_argument("--agents", default=None, help="comma-separated agent indices (default: the whole team)")
    agents.add_argument("--process-per-agent", action="store_true", help="one process per agent (default: one for all)")
    agents.add_argument(
        "--mode",
        choices=("sync", "free"),
        default="sync",
        help="sync (default): one command per step, on the scan and the team's odometry of its stamp, as the simulator's "
        "synchronous mode needs; free: on every scan (a robot)",
    )
    agents.add_argument("--sim-time", action="store_true", help="follow the simulator's /clock (use_sim_time), in free mode")
    agents.add_argument("--no-filter", action="store_true", help="send the policy's actions without the safety filter")
    agents.add_argument(
        "--filter-disturbances",
        default="",
        metavar="NAME|FILE",
        help="the errors the safety filter stays safe under, declared by disturbances: a profile (ideal, realistic, "
        "harsh) or a YAML file (default: the policy's task's)",
    )
    _add_ros_options(agents)


def _add_ros_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--ros-args",
        dest="ros_args",
        nargs=argparse.REMAINDER,
        default=[],
        help="the rest goes to ROS, e.g. --ros-args -p input_timeout:=2.0 (a parameter of every node of the process)",
    )
    parser.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the environment's, else 0)")
    parser.add_argument(
        "--discovery",
        choices=tuple(DISCOVERY_RANGES),
        default="localhost",
        help="ROS_AUTOMATIC_DISCOVERY_RANGE (default localhost: nothing leaves this machine; subnet to reach robots)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m sb3_formation.ros``."""
    parser = OneLineParser(prog="python -m sb3_formation.ros", description=__doc__.splitlines()[0])
    add_arguments(parser.add_subparsers(dest="command", required=True), "an exported policy (.onnx)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m sb3_formation.ros``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    _die_with_parent()
    try:
        check_arguments(args)
        set_ros_environment(args.domain_id, args.discovery)
        if args.command == "sim":
            return run_sim(args)
        return run_agents(args, argv)
    except ImportError as error:  # no rclpy, or no message package
        print(f"sb3_formation.ros: error: the nodes need {error.name}: pip install 'sb3-formation[ros]'", file=sys.stderr)
        return 2
    except (ValueError, OSError, RuntimeError) as error:
        print(f"sb3_formation.ros: error: {error}", file=sys.stderr)
        return 2


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse bad options in one line before anything starts."""
    if not Path(args.model).is_file():
        raise FileNotFoundError(
            f"no exported policy at {args.model}: write one with `sb3-formation export TARGET --onnx FILE`"
        )
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        raise ValueError(f"--domain-id {args.domain_id} is not a ROS 2 domain id (0 to 232)")
    from sb3_formation.ros.onboard import check_disturbances

    for option, value in (
        ("--disturbances", getattr(args, "disturbances", "")),
        ("--filter-disturbances", getattr(args, "filter_disturbances", "")),
    ):
        if value:
            check_disturbances(option, value)
    if args.command == "sim":
        if not 1 <= args.stage <= 3:
            raise ValueError(f"--stage {args.stage} is not a curriculum stage (1, 2 or 3)")
        if args.episodes < 1:
            raise ValueError(f"--episodes must be at least 1, got {args.episodes}")
        if not args.rate > 0 or not args.command_timeout > 0:
            raise ValueError(f"--rate and --command-timeout must be > 0, got {args.rate} and {args.command_timeout}")
        if args.rate < MIN_RATE:
            raise ValueError(f"--rate {args.rate:g} is below {MIN_RATE:g}: a step would wait more than a thousand times dt")
        if args.out is not None and args.out.suffix != ".npz":
            raise ValueError(f"--out {args.out}: the episodes are written as an .npz file")
        if args.out is not None and args.out.exists():
            raise FileExistsError(f"{args.out} exists: choose another --out (nothing is overwritten)")


def set_ros_environment(domain_id: int | None, discovery: str) -> None:
    """``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE`` for this process and its children (before rclpy starts)."""
    if domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY_RANGES[discovery]


def agent_indices(text: str | None, n_agents: int) -> list[int]:
    """The agents ``--agents`` names (default: all ``n_agents``)."""
    if text is None:
        return list(range(n_agents))
    try:
        indices = [int(part) for part in text.split(",")]
    except ValueError:
        raise ValueError(f"--agents takes comma-separated agent indices, got {text!r}") from None
    wrong = [index for index in indices if not 0 <= index < n_agents]
    if wrong or len(set(indices)) != len(indices):
        raise ValueError(f"--agents {text}: indices must be distinct and within 0-{n_agents - 1} (a team of {n_agents})")
    return indices


def run_agents(args: argparse.Namespace, argv: list[str]) -> int:
    """Run the agent nodes until interrupted: in this process, or one child process per agent (each started with
    ``argv``, this command's arguments, for its one agent)."""
    from sb3_formation.runtime import load_onnx_policy

    policy = load_onnx_policy(args.model, threads=1)
    indices = agent_indices(args.agents, policy.config.n_agents)
    if args.process_per_agent and len(indices) > 1:
        ros_at = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
        own = [arg for arg in argv[:ros_at] if arg != "--process-per-agent"]
        own = [arg for position, arg in enumerate(own) if not _is_agents_option(own, position)]
        commands = [
            [sys.executable, "-m", "sb3_formation.ros", *own, "--agents", str(index), *argv[ros_at:]] for index in indices
        ]
        return _run_children(commands)
    from rclpy.parameter import Parameter

    from sb3_formation.ros.agent_node import AgentNode
    from sb3_formation.ros.onboard import AgentSettings

    def make_nodes() -> list[Any]:
        return [
            AgentNode(
                policy,
                AgentSettings(
                    agent=index,
                    synchronous=args.mode == "sync",
                    safety_filter=not args.no_filter,
                    filter_disturbances=args.filter_disturbances,
                ),
                name=f"formation_agent_{index}",
                namespace=AGENT_NAMESPACE.format(index=index),
                parameter_overrides=[Parameter("use_sim_time", value=args.sim_time)],
            )
            for index in indices
        ]

    return _spin(make_nodes, args.ros_args)


def _is_agents_option(arguments: list[str], position: int) -> bool:
    """Whether ``arguments[position]`` is ``--agents`` or its value (``--agents=...`` included)."""
    argument = arguments[position]
    return (
        argument == "--agents" or argument.startswith("--agents=") or (position > 0 and arguments[position - 1] == "--agents")
    )


def run_sim(args: argparse.Namespace) -> int:
    """Run the simulator node until its episodes are played; print them, and write them to ``--out``."""
    if args.out is not None:
        check_out(args.out)
    from sb3_formation.ros.sim_node import SimNode, SimSettings
    from sb3_formation.runtime import OnnxPolicy

    config = OnnxPolicy(args.model, threads=1).config
    changes: dict[str, Any] = {"stage": args.stage} | ({"scenes": args.scenes} if args.scenes else {})
    config = config.replace(**changes)
    settings = SimSettings(
        seed=args.seed,
        episodes=args.episodes,
        synchronous=args.mode == "sync",
        rate=args.rate,
        command_timeout=args.command_timeout,
        see_through_agents=args.see_through_agents,
        disturbances=args.disturbances,
    )
    nodes: list[Any] = []
    saved = [0]  # episodes written to --out

    def make_nodes() -> list[Any]:
        nodes.append(SimNode(config, settings))
        return nodes

    def save() -> None:  # every episode as it ends: a simulator that fails later keeps those it played
        if args.out is not None and nodes and len(nodes[0].results) > saved[0]:
            nodes[0].save(args.out)
            saved[0] = len(nodes[0].results)

    def done() -> bool:
        save()
        return bool(nodes) and nodes[0].done

    try:
        code = _spin(make_nodes, args.ros_args, until=done)
    finally:  # also on an error (a command timeout): the episodes played are printed and kept
        if nodes:
            save()
            for result in nodes[0].results:
                print(f"seed {result.seed}: {'success' if result.success else 'failure'} in {result.steps} steps")
    return code


def check_out(out: Path) -> None:
    """Refuse an ``--out`` that cannot be written (a read-only or missing folder that cannot be made) in one line,
    before anything is flown: a temporary file is made beside it, as the writer will, and removed."""
    from sb3_formation.utils.files import temporary_beside

    try:
        temporary_beside(out).unlink()
    except OSError as error:
        raise OSError(f"--out {out}: cannot write there ({error.strerror or error})") from None


def _spin(make_nodes: Any, ros_arguments: list[str], until: Any = None) -> int:
    """Start rclpy, spin the nodes ``make_nodes()`` builds in one executor until ``until()`` or an interrupt (Ctrl-C or
    SIGTERM), then shut down."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    _stop_on_signals()
    # Only the handlers above stop the process, in its main thread: rclpy's own (its default) would at the same time
    # shut the context down and trigger the executor's guard conditions from a second thread, while the main thread
    # destroys them.
    arguments = ["sb3_formation.ros", "--ros-args", *ros_arguments] if ros_arguments else None
    rclpy.init(args=arguments, signal_handler_options=SignalHandlerOptions.NO)
    executor = SingleThreadedExecutor()
    try:
        for node in make_nodes():
            executor.add_node(node)
        while until is None or not until():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        rclpy.try_shutdown()
    return 0


def _interrupt(number: int, frame: Any) -> None:
    """SIGTERM as Ctrl-C: the nodes shut down cleanly."""
    raise KeyboardInterrupt


def _stop_on_signals() -> None:
    """Ctrl-C and SIGTERM stop this process cleanly, also where SIGINT was ignored when it started (``nohup``, a
    background job); SIGUSR1 prints the stack of every thread to stderr (where a process that does not stop is)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _interrupt)
    faulthandler.register(signal.SIGUSR1, all_threads=True)


def _run_children(commands: list[list[str]], stop_timeout: float = STOP_TIMEOUT) -> int:
    """Run one child process per command until all end or this one is stopped (Ctrl-C or SIGTERM); then each child still
    running gets SIGTERM, which shuts its node down cleanly. A child still running ``stop_timeout`` s later prints its
    threads' stacks (SIGUSR1) and is killed, and this process then returns 1.

    :param stop_timeout: (s) how long the children may take to end after SIGTERM
    """
    _stop_on_signals()
    environment = os.environ | {PARENT_VARIABLE: str(os.getpid())}
    children = [subprocess.Popen(command, env=environment) for command in commands]
    try:
        codes = [child.wait() for child in children]
    except KeyboardInterrupt:
        codes = []
    finally:
        stuck = _stop_children(children, commands, stop_timeout)
    return 1 if stuck else max(codes, default=0)


def _stop_children(children: list[subprocess.Popen], commands: list[list[str]], stop_timeout: float) -> bool:
    """SIGTERM each running child and wait up to ``stop_timeout`` s for all to end; kill the ones that did not (each
    first prints its threads' stacks) and name their ``commands``. Return whether any was killed."""
    for child in children:
        if child.poll() is None:
            child.terminate()
    deadline = time.monotonic() + stop_timeout
    stuck = []
    for child, command in zip(children, commands, strict=True):
        try:
            child.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            stuck.append((child, command))
            child.send_signal(signal.SIGUSR1)
    if stuck:
        time.sleep(1.0)  # (s) time to write the stacks
    for child, command in stuck:
        child.kill()
        child.wait()
        print(f"killed `{' '.join(command[1:])}`: it had not ended {stop_timeout:g} s after SIGTERM", file=sys.stderr)
    return bool(stuck)


def _die_with_parent() -> None:
    """In an agent's process of ``--process-per-agent`` (:data:`PARENT_VARIABLE` set): end with the parent, even if it
    is killed with SIGKILL and cannot stop its children. On Linux the kernel sends SIGTERM (``prctl``'s
    ``PR_SET_PDEATHSIG``, which shuts the node down cleanly); elsewhere a thread looks for a new parent every 0.5 s. A
    parent that died before this ran is seen at once."""
    parent = os.environ.pop(PARENT_VARIABLE, "")
    if not parent.isdigit():
        return
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    else:
        import threading

        def watch() -> None:
            while os.getppid() == int(parent):
                time.sleep(0.5)
            os.kill(os.getpid(), signal.SIGTERM)

        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    if os.getppid() != int(parent):  # the parent died before the line above
        os.kill(os.getpid(), signal.SIGTERM)
