"""The README and the documentation site: the README's shape, code blocks that run as written, command lines the CLI
accepts, the shipped policies' table as the command prints it, an API page for every module, and a strict build."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import re
import shlex
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import pytest

from sb3_formation.cli import _attach_negative_values, build_parser, main
from sb3_formation.experiment.pretrained import pretrained_names

ROOT = Path(__file__).parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
#: Pages whose ```python blocks run here, as written (the libraries page's run in tests/test_integrations.py).
RUN_PAGES = [README, DOCS / "getting-started.md", DOCS / "environment.md", DOCS / "scenes.md", DOCS / "evaluation.md"]
#: Modules without an API section: the deprecated alias of experiment.recipes and the ``python -m`` entry point.
NOT_IN_API = {"sb3_formation.experiment.setups", "sb3_formation.cli.__main__"}


def code_blocks(path: Path, language: str) -> list[str]:
    """The fenced blocks of ``language`` in a Markdown file, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", path.read_text(), flags=re.DOTALL | re.MULTILINE)


def command_lines(path: Path) -> list[str]:
    """The ``sb3-formation`` command lines of a Markdown file's bash blocks (continuations joined, comments dropped)."""
    lines = []
    for block in code_blocks(path, "bash"):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "sb3-formation":
                lines.append(line)
    return lines


def test_the_readme_introduces_in_at_most_200_lines_and_opens_with_the_two_commands() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 200
    assert lines[3].startswith("make run ") and lines[4].startswith("make test ")
    assert "docs/getting-started.md" in README.read_text()
    # no development diary: no first person, no issue numbers, no dates
    text = README.read_text()
    assert not re.search(r"\b(I|my|we|our)\b", text), re.findall(r".*\b(?:I|my|we|our)\b.*", text)
    assert not re.search(r"\bissue \d+|\b20\d\d-\d\d-\d\d\b", text)


#: The README and every page of the site.
PAGES = [README, *sorted(DOCS.glob("*.md")), *sorted(DOCS.glob("notes/*.md"))]


@pytest.mark.parametrize("page", PAGES, ids=lambda page: str(page.relative_to(ROOT)))
def test_every_command_line_shown_is_accepted_by_the_cli(page: Path) -> None:
    """Each ``sb3-formation ...`` line of the README's and the pages' bash blocks parses with the command's own parser
    (placeholders such as ``runs/<run>`` are paths, which the parser does not open)."""
    parser = build_parser()
    for line in command_lines(page):
        try:
            parser.parse_args(_attach_negative_values(shlex.split(line, comments=True)[1:]))
        except SystemExit as error:
            raise AssertionError(f"{page.name}: the CLI rejects {line!r}") from error


def test_at_least_the_getting_started_commands_are_checked() -> None:
    assert len(command_lines(README)) >= 6 and len(command_lines(DOCS / "getting-started.md")) >= 5


@pytest.mark.slow
@pytest.mark.parametrize("page", RUN_PAGES, ids=lambda page: page.name)
def test_the_python_blocks_run_as_written(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The page's ```python blocks, in order, in one namespace (files they write go to a temporary folder)."""
    blocks = code_blocks(page, "python")
    assert blocks
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, Any] = {}
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore", UserWarning)
        for block in blocks:
            exec(block, namespace)  # the page's own code
    if "result" in namespace:  # an evaluation: every episode played and summarised
        summary = namespace["result"].summary
        assert summary["episodes"] == len(namespace["result"].episodes) and 0.0 <= summary["success_rate"] <= 1.0


def test_the_readmes_shipped_policies_table_is_what_the_command_prints() -> None:
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["pretrained"]) == 0
    table = printed.getvalue().strip().splitlines()
    assert len(table) == 2 + len(pretrained_names())
    readme = README.read_text().splitlines()
    start = readme.index(table[0])
    assert readme[start : start + len(table)] == table


def package_modules() -> list[str]:
    """Every module of the package, by its dotted name (packages by their own name)."""
    source = ROOT / "src"
    names = []
    for path in sorted((source / "sb3_formation").rglob("*.py")):
        parts = path.relative_to(source).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_every_module_has_a_section_in_the_api_reference() -> None:
    documented = set()
    for page in (DOCS / "api").glob("*.md"):
        documented |= set(re.findall(r"^::: (\S+)$", page.read_text(), flags=re.MULTILINE))
    missing = sorted(set(package_modules()) - documented - NOT_IN_API)
    assert not missing, f"modules without an API section in docs/api/: {missing}"
    assert not documented - set(package_modules()), "API sections of modules that do not exist"


@pytest.mark.slow
def test_the_site_builds_in_strict_mode(tmp_path: Path) -> None:
    """``mkdocs build --strict``: a broken link, a page missing from the nav, an unknown API object or a docstring
    mkdocstrings cannot read fails the build."""
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (the docs extra: pip install -e '.[docs]')")
    paths = [str(ROOT / "src"), *filter(None, [os.environ.get("PYTHONPATH")])]
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")]
    built = subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "env" / "index.html").is_file()
    assert "pretrained:mixed-ch5-bearing" in (tmp_path / "site" / "pretrained" / "index.html").read_text()
