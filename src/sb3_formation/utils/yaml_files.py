"""YAML as users write it: PyYAML follows YAML 1.1, which reads ``3e-4`` (a number to anyone writing a learning rate)
as a string because it has no dot. :func:`read_yaml` reads it, and ``1E5``, ``-2e+3``, as numbers."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import yaml

#: The most nodes a YAML text may hold once its aliases are expanded: far above any recipe (a shipped recipe has
#: about 100), far below a "billion laughs" text whose few lines of nested anchors expand to 10^9 items.
MAX_YAML_NODES = 100_000


class NumberLoader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads exponent numbers without a dot (``3e-4``) as floats, and refuses a text
    whose aliases expand it beyond :data:`MAX_YAML_NODES` nodes, counted as it is composed, before anything is built
    (PyYAML shares an aliased node, but any code that walks or copies the data expands it)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._sizes: dict[int, int] = {}  # expanded size of each composed node, by id

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        node = super().compose_node(parent, index)
        if node is not None and id(node) not in self._sizes:
            children = node.value if isinstance(node, yaml.SequenceNode) else []
            if isinstance(node, yaml.MappingNode):
                children = [child for pair in node.value for child in pair]
            size = 1 + sum(self._sizes.get(id(child), 1) for child in children)
            if size > MAX_YAML_NODES:
                raise yaml.YAMLError(
                    f"its aliases expand it to more than {MAX_YAML_NODES} nodes (nested anchors): write the values out"
                )
            self._sizes[id(node)] = size
        return node


NumberLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def read_yaml(text: str, source: str) -> Any:
    """The data of YAML ``text`` (``None`` for an empty text), numbers read as users write them.

    :param text: the YAML text
    :param source: where the text comes from (a file's path, an option), for the error message
    :raises ValueError: the text is not valid YAML (the message names ``source`` and the parser's first line)
    """
    try:
        return yaml.load(text, Loader=NumberLoader)  # a SafeLoader: builds plain data only
    except yaml.YAMLError as error:
        reason = " ".join(str(error).split())
        raise ValueError(f"{source} is not valid YAML: {reason}") from None


def read_yaml_file(path: str | os.PathLike[str]) -> Any:
    """The data of a YAML file (see :func:`read_yaml`).

    :raises FileNotFoundError: no such file
    :raises ValueError: not UTF-8 text, or not valid YAML (the message names the file)
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file {path}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path} is not UTF-8 text (byte {error.start}): a YAML file must be") from None
    return read_yaml(text, str(path))
