"""ROS 2 messages to and from the package's arrays: ``LaserScan``, ``Odometry``, ``PointStamped``, ``Twist``, time, and
the policy's messages between ring neighbours as ``JointState``.

Units and frames follow REP 103 (m, rad, m/s; x forward, y left, yaw anti-clockwise) and REP 105 (a world frame shared
by the team, default ``map``; each robot's ``base_link``). Needs rclpy's message packages:
``pip install 'sb3-formation[ros]'``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import JointState, LaserScan

from sb3_formation.env.dynamics import DynamicsModel, turned
from sb3_formation.ros.scans import Scan

#: Nanoseconds in a second.
NANOSECONDS = 1_000_000_000
#: How far from 1 the norm of an orientation quaternion may be (drivers round them); further, it is not a rotation.
QUATERNION_TOLERANCE = 0.01


def stamp_of(seconds: float) -> Time:
    """A message time stamp of ``seconds`` (>= 0), to the nanosecond."""
    nanoseconds = round(seconds * NANOSECONDS)
    return Time(sec=nanoseconds // NANOSECONDS, nanosec=nanoseconds % NANOSECONDS)


def nanoseconds_of(stamp: Any) -> int:
    """A message time stamp (``builtin_interfaces/Time``) in nanoseconds."""
    return int(stamp.sec) * NANOSECONDS + int(stamp.nanosec)


def yaw_of(orientation: Any) -> float:
    """The yaw (rad, anti-clockwise about z) of a quaternion (``geometry_msgs/Quaternion``); roll and pitch ignored."""
    x, y, z, w = orientation.x, orientation.y, orientation.z, orientation.w
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def odometry_message(
    stamp: Time, frames: tuple[str, str], position: np.ndarray, yaw: float, body_velocity: np.ndarray, turn_rate: float
) -> Odometry:
    """An ``Odometry`` of an agent: its pose in the world frame, its twist in its body frame (REP 105).

    :param frames: the world frame (the header's) and the agent's body frame (the child frame)
    :param position: ``(2,)`` (m) in the world frame
    :param yaw: heading (rad) in the world frame
    :param body_velocity: ``(2,)`` (m/s) in the body frame (x forward, y left)
    :param turn_rate: (rad/s)
    """
    message = Odometry()
    message.header.stamp, (message.header.frame_id, message.child_frame_id) = stamp, frames
    message.pose.pose.position.x, message.pose.pose.position.y = float(position[0]), float(position[1])
    message.pose.pose.orientation.z, message.pose.pose.orientation.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)
    message.twist.twist.linear.x, message.twist.twist.linear.y = float(body_velocity[0]), float(body_velocity[1])
    message.twist.twist.angular.z = float(turn_rate)
    return message


def odometry_state(message: Odometry) -> tuple[np.ndarray, float, np.ndarray]:
    """An ``Odometry``'s position ``(2,)`` (m), yaw (rad) and velocity ``(2,)`` (m/s), all in the world frame.

    An orientation that is not a unit quaternion (within :data:`QUATERNION_TOLERANCE`) gives a NaN yaw and velocity,
    which the on-board checks refuse (:func:`~sb3_formation.ros.onboard.team_problem`)."""
    pose, twist = message.pose.pose, message.twist.twist
    q = pose.orientation
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w) if _finite(q.x, q.y, q.z, q.w) else math.nan
    yaw = yaw_of(q) if abs(norm - 1.0) <= QUATERNION_TOLERANCE else math.nan
    velocity = turned(np.array([twist.linear.x, twist.linear.y]), yaw)  # body frame to world (exact at yaw 0)
    return np.array([pose.position.x, pose.position.y]), yaw, velocity


def _finite(*values: float) -> bool:
    return all(math.isfinite(value) for value in values)


def scan_message(
    stamp: Time, frame: str, ranges: np.ndarray, angle_min: float, range_min: float, range_max: float
) -> LaserScan:
    """A full-circle ``LaserScan`` of ``len(ranges)`` beams, anti-clockwise from ``angle_min`` (rad, in ``frame``)."""
    message = LaserScan()
    message.header.stamp, message.header.frame_id = stamp, frame
    increment = 2.0 * math.pi / len(ranges)
    message.angle_min, message.angle_increment = float(angle_min), increment
    message.angle_max = float(angle_min + increment * (len(ranges) - 1))
    message.range_min, message.range_max = float(range_min), float(range_max)
    message.ranges = np.asarray(ranges, dtype=np.float32).tolist()
    return message


def scan_of(message: LaserScan) -> Scan:
    """The fields of a ``LaserScan`` that place its returns."""
    return Scan(
        np.asarray(message.ranges, dtype=np.float64),
        float(message.angle_min),
        float(message.angle_increment),
        float(message.range_min),
        float(message.range_max),
    )


def goal_message(stamp: Time, world_frame: str, goal: np.ndarray) -> PointStamped:
    """The team's goal (m) in the world frame; its stamp is the time it was given."""
    message = PointStamped()
    message.header.stamp, message.header.frame_id = stamp, world_frame
    message.point.x, message.point.y = float(goal[0]), float(goal[1])
    return message


def twist_message(command: np.ndarray, model: DynamicsModel, yaw: float) -> Twist:
    """The ``Twist`` of a command (:meth:`~sb3_formation.env.dynamics.DynamicsModel.command`) in the robot's body frame
    (:meth:`~sb3_formation.env.dynamics.DynamicsModel.twist`): a holonomic agent's world velocity turned by -yaw into
    ``linear.x, linear.y``; a unicycle's forward speed as ``linear.x`` and turn rate as ``angular.z``.

    :param model: the task's dynamics (:func:`~sb3_formation.env.dynamics.dynamics_model`)
    :param yaw: the robot's heading (rad)
    """
    message = Twist()
    message.linear.x, message.linear.y, message.angular.z = model.twist(command, yaw)
    return message


def twist_command(message: Twist, model: DynamicsModel, yaw: float) -> np.ndarray:
    """The command a ``Twist`` gives (the inverse of :func:`twist_message`)."""
    return model.twist_command((message.linear.x, message.linear.y, message.angular.z), yaw)


def policy_message(stamp: Time, values: np.ndarray) -> JointState:
    """The message a policy's agent sends its ring neighbours, as a ``JointState``: ROS 2's own stamped vector of named
    values (a message type of one's own would need a ROS build to generate it). The stamp is the step's the agent acted
    on; the names are ``m0`` ... ``m{M-1}``; ``position`` holds the values.

    :param stamp: the stamp of the inputs the agent acted on
    :param values: ``(M,)`` the message
    """
    message = JointState()
    message.header.stamp = stamp
    message.name = [f"m{index}" for index in range(len(values))]
    message.position = [float(value) for value in values]
    return message


def policy_message_of(message: JointState) -> tuple[int, np.ndarray]:
    """The stamp (ns) and the values of a policy message (:func:`policy_message`)."""
    return nanoseconds_of(message.header.stamp), np.array(message.position, dtype=np.float32)
