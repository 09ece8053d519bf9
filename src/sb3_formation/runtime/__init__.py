"""Running an exported policy without torch or Stable-Baselines3: numpy, onnx and onnxruntime only (``docs/export.md``).

``pip install 'sb3-formation[runtime]'`` installs onnx and onnxruntime. :class:`OnnxPolicy` is a
:class:`~sb3_formation.controllers.base.TeamPolicy`: ``evaluate``, ``render`` and ``compare`` run an exported file as
they run any target, and a robot calls :meth:`OnnxPolicy.agent_actions` for the agents it hosts.
"""

from sb3_formation.runtime.onnx_policy import OnnxPolicy, PolicyMetadata, load_onnx_policy

__all__ = ["OnnxPolicy", "PolicyMetadata", "load_onnx_policy"]
