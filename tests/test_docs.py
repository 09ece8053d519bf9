"""The README and the documentation site: the README's shape, code blocks that run as written, command lines the CLI
accepts, the shipped policies' table as the command prints it, an API page for every module, a user's manual without
dates of work, no issue numbers anywhere, and a strict build."""

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
#: Modules without an API section: the ``python -m`` entry point.
NOT_IN_API = {"sb3_formation.cli.__main__", "sb3_formation.ros.__main__"}
#: The pages of the user's manual: every page of the site outside the research notes (docs/research/).
MANUAL_PAGES = [*sorted(DOCS.glob("*.md")), *sorted(DOCS.glob("api/*.md"))]
#: An ISO date (2026-11-25): a date of work, which the manual's pages do not carry.
ISO_DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
#: A citation of an issue tracker's entry by number ("issue 17", "issues #3", "#28"); a link to another project's
#: issue page (``.../issues/251``) is not one.
ISSUE_NUMBER = re.compile(r"\bissues? *#? *\d+|(?<![\w&/#])#\d+\b", flags=re.IGNORECASE)


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


def test_the_readme_says_what_the_package_is_and_shows_it_before_the_two_commands() -> None:
    """At most 200 lines: the title, what the package is, a picture of it, then the first code block, which holds the
    two make commands (both targets of the Makefile), before any other command."""
    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) <= 200
    first_block = next(index for index, line in enumerate(lines) if line.startswith("```"))
    assert lines[first_block] == "```bash"
    assert lines[first_block + 1].startswith("make run ") and lines[first_block + 2].startswith("make test ")
    introduction = lines[1:first_block]
    assert any("Stable-Baselines3" in line for line in introduction)
    pictures = [match for line in introduction for match in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", line)]
    assert pictures and all((ROOT / picture).is_file() for picture in pictures), pictures
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^run:", makefile, flags=re.MULTILINE) and re.search(r"^test:", makefile, flags=re.MULTILINE)
    assert "docs/getting-started.md" in text
    # no development diary: no first person, no issue numbers, no dates
    text = README.read_text()
    assert not re.search(r"\b(I|my|we|our)\b", text), re.findall(r".*\b(?:I|my|we|our)\b.*", text)
    assert not re.search(r"\bissue \d+|\b20\d\d-\d\d-\d\d\b", text)


#: The README and every page of the site.
PAGES = [README, *sorted(DOCS.glob("*.md")), *sorted(DOCS.glob("research/*.md"))]


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


@pytest.mark.parametrize("page", MANUAL_PAGES, ids=lambda page: str(page.relative_to(ROOT)))
def test_the_users_manual_carries_no_dates_of_work(page: Path) -> None:
    """A page of the manual says what holds, not when it was done: a measured figure's date and CPU are the first line
    of the output file the page includes (under docs/measurements/), or one "measured on" line beside its table."""
    dated = [line for line in page.read_text().splitlines() if ISO_DATE.search(line)]
    assert not dated, f"{page.relative_to(ROOT)}: {dated}"


def issue_citing_files() -> list[Path]:
    """Every text file of the docs, the benchmarks, the notebooks and the project's top-level documents."""
    files = [ROOT / name for name in ("README.md", "CHANGELOG.md", "mkdocs.yml", "pyproject.toml")]
    files += [path for path in sorted(DOCS.rglob("*")) if path.suffix in {".md", ".txt", ".py", ".yaml", ".yml", ".json"}]
    files += sorted((ROOT / "benchmarks").glob("*.py")) + sorted((ROOT / "notebooks").glob("*.*"))
    return [path for path in files if path.is_file()]


def test_no_doc_benchmark_or_readme_cites_an_issue_number() -> None:
    """An issue tracker a reader cannot reach explains nothing: a line says what holds and why."""
    cited = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}"
        for path in issue_citing_files()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        if ISSUE_NUMBER.search(line)
    ]
    assert not cited, "\n".join(cited)


def test_the_date_and_issue_checks_catch_what_they_are_for() -> None:
    assert ISO_DATE.search("measured 2026-11-25 on an AMD EPYC") and not ISO_DATE.search("measured in November 2026")
    assert ISSUE_NUMBER.search("Targets (issue 17): at least") and ISSUE_NUMBER.search("fixed in #28")
    assert not ISSUE_NUMBER.search("[a report](https://github.com/facebookresearch/BenchMARL/issues/251)")
    assert not ISSUE_NUMBER.search("[the cost](safety.md#cost), &#39;, # 3 agents")


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
    assert (tmp_path / "site" / "research" / "index.html").is_file()
    assert "pretrained:mixed-ch5-bearing" in (tmp_path / "site" / "pretrained" / "index.html").read_text()
