"""The guide cannot rot: its code runs, its links resolve, its command table is the CLI's.

* every ```python block of README.md and docs/**/*.md runs: a file's blocks in order, in a
  namespace of its own; all files in one fresh subprocess (as a script starts: float32 until a
  page calls ``racing_env.configure_for_racing()``, which every page that plans does; the
  files share its compiled solvers). A block
  opts out only with the HTML comment ``<!-- no-test: reason -->`` on the line before it, for
  blocks that need a trained model or minutes;
* README.md stays a guide: at most 400 lines;
* no diary in the guide or the code: no "session", "scratch" or "/tmp/" (outside the few
  legitimate uses listed in ``DIARY_ALLOWED``), and no date in a .py file of the packages;
* the README's command table lists exactly the subcommands of ``racing --help``, with their
  one-line helps;
* relative links in README.md and docs/*.md point to files (and headings) that exist.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOC_FILES = sorted([README, *(ROOT / "docs").rglob("*.md")])
PACKAGES = ("racing_env", "planners", "experiments")
MAX_README_LINES = 400
BLOCK_TIMEOUT_S = 900  # every file's blocks together (about a minute and a half on 2 cores)

OPT_OUT = re.compile(r"<!--\s*no-test:\s*\S.*-->")
FENCE = re.compile(r"^(\s*)```([\w+-]*)(.*)$")
PYTHON_FENCES = ("python", "py", "python3")

# Lines the diary grep matches that are not diary: (path relative to the root, or "" for any
# file; a regex the matching line must contain). Keep it narrow, one entry per legitimate use.
# Python's own keyword `start_new_session` (subprocess.Popen: a new process group, so that
# Ctrl-C can be sent to a command and its workers) is the only such use.
DIARY_ALLOWED: list[tuple[str, str]] = [
    ("", r"\bstart_new_session\b"),
]
DIARY = re.compile(r"session|scratch|/tmp/", re.IGNORECASE)
DATE = re.compile(r"\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b")


def _relative(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def python_blocks(path: Path) -> list[tuple[int, str, bool]]:
    """The ```python blocks of a Markdown file: (line of the opening fence, code, opted out)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        match = FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        indent, language, _ = match.groups()
        start = i
        body = []
        i += 1
        while i < len(lines) and not re.match(rf"^{re.escape(indent)}```\s*$", lines[i]):
            body.append(lines[i])
            i += 1
        i += 1
        if language.lower() not in PYTHON_FENCES:
            continue
        previous = next((lines[j] for j in range(start - 1, -1, -1) if lines[j].strip()), "")
        code = textwrap.dedent("\n".join(body))
        blocks.append((start + 1, code, bool(OPT_OUT.search(previous))))
    return blocks


def _files_with_code() -> list[Path]:
    return [p for p in DOC_FILES if any(not skip for _, _, skip in python_blocks(p))]


_RESULT_MARK = "@@doc-code-results@@"


def _script(paths: list[Path]) -> str:
    """One program running every file's blocks: each file's in order in a namespace of its
    own, a failing block ending its file (not the others); the last line of the output is
    ``_RESULT_MARK`` and a JSON object, file -> the failing block's traceback or None."""
    parts = ["import json, sys, traceback", "__results = {}"]
    for path in paths:
        name = _relative(path)
        body = [f"    __ns = {{'__name__': '__main__'}}", f"    print('=== {name}', flush=True)"]
        for line, code, skip in python_blocks(path):
            if not skip:
                body.append(f"    exec(compile({code!r}, {f'{name}:{line}'!r}, 'exec'), __ns)")
        parts.append(
            "try:\n" + "\n".join(body) + "\n"
            f"    __results[{name!r}] = None\n"
            "except BaseException:\n"
            f"    __results[{name!r}] = traceback.format_exc()"
        )
    parts.append(f"print({_RESULT_MARK!r} + json.dumps(__results), flush=True)")
    return "\n".join(parts)


def test_python_blocks_run() -> None:
    """Every file's blocks, run in one fresh subprocess (JAX's defaults, as a script starts: a
    page that plans sets float64 itself; the files share its compiled solvers, each file has
    its own namespace).
    Fails naming every file whose blocks failed, with the failing block's traceback (its
    file name is ``path:line`` of the block)."""
    result = subprocess.run(
        [sys.executable, "-c", _script(_files_with_code())],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=BLOCK_TIMEOUT_S,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )
    last = result.stdout.rstrip().rpartition("\n")[2]
    assert result.returncode == 0 and last.startswith(_RESULT_MARK), (
        f"the docs' code did not run to its end\n{result.stderr[-4000:]}\n{result.stdout[-1000:]}"
    )
    failures = {name: trace for name, trace in json.loads(last[len(_RESULT_MARK):]).items() if trace}
    assert not failures, "python blocks failed in " + ", ".join(failures) + "\n" + "\n".join(
        f"--- {name}\n{trace[-3000:]}" for name, trace in failures.items())


def test_opt_outs_give_a_reason_and_are_few() -> None:
    for path in DOC_FILES:
        blocks = python_blocks(path)
        skipped = [line for line, _, skip in blocks if skip]
        assert len(skipped) <= max(1, len(blocks) // 2), (
            f"{_relative(path)}: too many blocks opted out of the test (lines {skipped})"
        )


def test_readme_is_a_guide_not_a_notebook() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"


def _diary_targets() -> list[Path]:
    files = [README, *(ROOT / "docs").rglob("*.md"), *(ROOT / "docs").rglob("*.toml")]
    for package in PACKAGES:
        files += [p for p in (ROOT / package).rglob("*") if p.is_file() and p.suffix in (".py", ".md", ".toml")]
    return sorted(files)


def _allowed(path: str, line: str) -> bool:
    return any((not prefix or path == prefix) and re.search(pattern, line) for prefix, pattern in DIARY_ALLOWED)


def test_no_diary_lines() -> None:
    found = []
    for path in _diary_targets():
        rel = _relative(path)
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if DIARY.search(line) and not _allowed(rel, line):
                found.append(f"{rel}:{number}: {line.strip()}")
    assert not found, "diary lines (session / scratch / /tmp/):\n" + "\n".join(found)


def test_no_dates_in_code() -> None:
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if DATE.search(line):
                    found.append(f"{_relative(path)}:{number}: {line.strip()}")
    assert not found, "dates in code:\n" + "\n".join(found)


def _cli_commands() -> dict[str, str]:
    from experiments.cli import build_parser

    parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return {choice.dest: choice.help for choice in action._choices_actions}
    raise AssertionError("racing has no subcommands")


def _readme_commands() -> dict[str, str]:
    rows = {}
    for line in README.read_text(encoding="utf-8").splitlines():
        match = re.match(r"^\|\s*`racing (\w[\w-]*)`\s*\|\s*(.*?)\s*\|\s*$", line)
        if match:
            rows[match.group(1)] = match.group(2)
    return rows


def test_readme_command_table_is_the_cli() -> None:
    cli, readme = _cli_commands(), _readme_commands()
    assert sorted(readme) == sorted(cli), f"README lists {sorted(readme)}, `racing --help` {sorted(cli)}"
    for name, help_text in cli.items():
        assert readme[name] == help_text, f"racing {name}: README says {readme[name]!r}, --help {help_text!r}"


LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown file (lower case, punctuation dropped, spaces -> -)."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
    anchors = set()
    for heading in re.findall(r"^#+\s+(.*?)\s*$", text, flags=re.MULTILINE):
        anchors.add(re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-"))
    return anchors


def test_relative_links_resolve() -> None:
    broken = []
    for path in [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.DOTALL)
        for match in LINK.finditer(text):
            target = match.group(1) or match.group(2)
            if re.match(r"^[a-z]+:", target):
                continue
            file_part, _, anchor = target.partition("#")
            linked = (path.parent / file_part) if file_part else path
            if not linked.exists():
                broken.append(f"{_relative(path)}: {target} (no such file)")
            elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
                broken.append(f"{_relative(path)}: {target} (no such heading)")
    assert not broken, "broken links:\n" + "\n".join(broken)


DOC_POINTER = re.compile(r'(docs/[\w/-]+\.md)(?:, "([^"]+)")?')


def test_code_points_to_docs_that_exist() -> None:
    """A docstring's ``docs/page.md`` (and ``docs/page.md, "Heading"``) names a page and heading
    that exist."""
    broken = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                for page, heading in DOC_POINTER.findall(line):
                    target = ROOT / page
                    if not target.exists():
                        broken.append(f"{_relative(path)}:{number}: {page} (no such page)")
                    elif heading and re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-") not in _anchors(target):
                        broken.append(f"{_relative(path)}:{number}: {page}, {heading!r} (no such heading)")
    assert not broken, "docs pointers in code that lead nowhere:\n" + "\n".join(broken)


def _racing_command_lines(path: Path) -> list[tuple[int, str]]:
    """The ``racing ...`` command lines of a Markdown file's shell blocks (continuations joined,
    comments dropped), with the line they start on."""
    commands, in_shell, pending, start = [], False, "", 0
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        match = FENCE.match(line)
        if match:
            in_shell = not in_shell and match.group(2) in ("bash", "sh", "shell", "console")
            continue
        if not in_shell:
            continue
        code = line.split(" #", 1)[0].rstrip() if not line.lstrip().startswith("#") else ""
        if not pending:
            start = number
        pending += " " + code.rstrip("\\").strip()
        if code.endswith("\\"):
            continue
        text, pending = pending.strip(), ""
        if text.startswith("racing ") and "$" not in text:
            commands.append((start, text))
    return commands


def test_documented_commands_parse() -> None:
    """Every ``racing ...`` line in the guide's shell blocks names a command and options that
    ``racing`` accepts (the parser only: nothing runs)."""
    from experiments.cli import build_parser

    bad = []
    for path in [README, *sorted((ROOT / "docs").rglob("*.md"))]:
        for number, text in _racing_command_lines(path):
            parser = build_parser()
            try:
                parser.parse_args(shlex.split(text)[1:])
            except SystemExit:
                bad.append(f"{_relative(path)}:{number}: {text}")
    assert not bad, "commands in the guide that racing refuses:\n" + "\n".join(bad)


# A path out of the checkout (e.g. "../shared/...") works only beside the development tree.
OUTSIDE_THE_REPOSITORY = re.compile(r"\.\./shared/")


def test_nothing_points_outside_the_repository() -> None:
    files = [*_diary_targets(), ROOT / "CHANGELOG.md", ROOT / "pyproject.toml", ROOT / "Makefile"]
    found = [f"{_relative(path)}:{number}: {line.strip()}"
             for path in files
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if OUTSIDE_THE_REPOSITORY.search(line)]
    assert not found, "references to files outside the repository:\n" + "\n".join(found)
    assert (ROOT / "LICENSE").is_file() and (ROOT / "docs" / "design.md").is_file()
