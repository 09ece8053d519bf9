"""MkDocs hooks of the documentation site (``hooks:`` in ``mkdocs.yml``).

Figures on the site come from the files that commands and benchmarks wrote, not from copies:

- ``<!-- output: sb3-formation <command> -->`` on a line of its own is replaced by what the command prints (only the
  commands of :data:`COMMANDS`, which read the package's files, print and write nothing);
- ``<!-- tables: docs/<folder>/<file> -->`` is replaced by the Markdown tables of that output file (its lines that
  start with ``|``), in order, each block as one table (blocks without rows are left out); the file lies under one of
  :data:`OUTPUT_FOLDERS`.

Whole output files are included with ``pymdownx.snippets`` (``--8<-- "docs/measurements/<file>"`` inside a fence).
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path
from typing import Any

#: Commands a page may include the output of (they only read the package's files).
COMMANDS = {"sb3-formation pretrained", "sb3-formation recipes"}
MARKER = re.compile(r"^<!-- output: (?P<command>[^>]*?) -->$", flags=re.MULTILINE)
TABLES = re.compile(r"^<!-- tables: (?P<path>[^>]*?) -->$", flags=re.MULTILINE)
#: The repository's root: paths of ``tables`` markers are relative to it.
ROOT = Path(__file__).resolve().parents[1]
#: Folders of output files whose tables a page may include: the figures the user's pages quote, and the raw outputs
#: of the research notes.
OUTPUT_FOLDERS = (ROOT / "docs" / "measurements", ROOT / "docs" / "research" / "results")


def command_output(command: str) -> str:
    """What ``command`` (one of :data:`COMMANDS`) prints."""
    if command not in COMMANDS:
        raise ValueError(f"docs may include the output of {sorted(COMMANDS)}, not {command!r}")
    from sb3_formation.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(shlex.split(command)[1:])
    if status != 0:
        raise RuntimeError(f"{command!r} exited with {status}")
    return printed.getvalue().rstrip("\n")


def file_tables(path: str) -> str:
    """The Markdown tables of an output file under one of :data:`OUTPUT_FOLDERS`, blocks separated by a blank line."""
    file = (ROOT / path).resolve()
    if not any(file.is_relative_to(folder) for folder in OUTPUT_FOLDERS) or not file.is_file():
        folders = ", ".join(str(folder.relative_to(ROOT)) for folder in OUTPUT_FOLDERS)
        raise FileNotFoundError(f"tables are read from files under {folders}, not {path!r}")
    blocks: list[list[str]] = [[]]
    for line in file.read_text(encoding="utf-8").splitlines():
        if line.startswith("|"):
            blocks[-1].append(line)
        elif blocks[-1]:
            blocks.append([])
    tables = ["\n".join(block) for block in blocks if len(block) > 2]  # a heading and a rule without rows: no table
    if not tables:
        raise ValueError(f"{path} holds no Markdown table")
    return "\n\n".join(tables)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Replace every marker of the page with the command's output or the file's tables."""
    markdown = MARKER.sub(lambda match: command_output(match["command"]), markdown)
    return TABLES.sub(lambda match: file_tables(match["path"]), markdown)
