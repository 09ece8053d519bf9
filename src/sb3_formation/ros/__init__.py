"""Policies on robots over ROS 2 (``docs/deployment.md``): an agent node per robot and the simulator as a node.

:mod:`~sb3_formation.ros.scans` and :mod:`~sb3_formation.ros.observer` turn what a robot senses into the policy's
observation and its action into a command, with numpy and the environment layer only; the nodes
(:mod:`~sb3_formation.ros.agent_node`, :mod:`~sb3_formation.ros.sim_node`) need rclpy and ROS 2's message packages:
``pip install 'sb3-formation[ros]'``. Nothing here imports torch.
"""
