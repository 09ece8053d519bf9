"""Running an exported policy without torch or Stable-Baselines3: numpy, onnx and onnxruntime only (``docs/export.md``).

``pip install 'sb3-formation[runtime]'`` installs onnx and onnxruntime. :func:`load_onnx_policy` loads an exported file
as a :class:`~sb3_formation.controllers.base.Policy` (:class:`OnnxPolicy`, behind the safety filter if it was trained
behind one): ``evaluate``, ``render`` and ``compare`` run it as they run any target (``predict``), and a robot calls
``agent_step`` for the agents it hosts (:mod:`sb3_formation.ros.onboard`).
"""

from sb3_formation.runtime.onnx_policy import OnnxPolicy, PolicyMetadata, load_onnx_policy

__all__ = ["OnnxPolicy", "PolicyMetadata", "load_onnx_policy"]
