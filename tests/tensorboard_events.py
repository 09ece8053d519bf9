"""Reading what a run wrote for TensorBoard, for the tests that check it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader
from tensorboard.plugins.hparams import plugin_data_pb2


def read_hparams(folder: Path) -> dict[str, Any]:
    """The HParams tab's data of a run folder: its ``metrics`` (tags) and ``hparams`` (name -> value)."""
    found: dict[str, Any] = {}
    for path in folder.glob("events.out.tfevents.*"):
        for event in LegacyEventFileLoader(str(path)).Load():
            for value in event.summary.value:
                if value.metadata.plugin_data.plugin_name != "hparams":
                    continue
                data = plugin_data_pb2.HParamsPluginData.FromString(value.metadata.plugin_data.content)
                if data.HasField("experiment"):
                    found["metrics"] = [info.name.tag for info in data.experiment.metric_infos]
                if data.HasField("session_start_info"):
                    hparams = data.session_start_info.hparams.items()
                    found["hparams"] = {name: getattr(item, item.WhichOneof("kind")) for name, item in hparams}
    return found
