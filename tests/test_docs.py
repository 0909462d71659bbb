"""The documentation as a user meets it: a README of at most 250 lines, links that resolve, no development
history in the docs or in what the project ships, and a CLI reference that is the programs' own help."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
# words that narrate the project's history ("session", "issue" or "call" and a number); CHANGELOG.md is exempt
HISTORY = re.compile(r"\b(session|issue|issues|call)s? ?\d", re.IGNORECASE)


def test_readme_is_short() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250, len(lines)


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    text = page.read_text()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" in target or target.startswith("mailto:"):
            continue
        assert (page.parent / target).exists(), f"{page.relative_to(ROOT)}: broken link {target}"


def test_no_history_in_docs_or_shipped_files() -> None:
    files = [*DOCS]
    for folder in ("jsgs", "jsgstools", "scripts", "tools", "benchmarks", ".ci"):
        for p in (ROOT / folder).rglob("*"):
            if p.suffix in {".py", ".sh", ".json", ".cu", ".cpp", ".md"} and p.is_file():
                files.append(p)
    files = [p for p in files if "docs/results/paper_protocol/runs" not in str(p)]
    hits = []
    for p in files:
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                hits.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not hits, "\n".join(hits[:20])


def test_cli_reference_is_current() -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import cli_reference
    finally:
        sys.path.pop(0)
    pages = cli_reference.pages()
    on_disk = {p.name: p.read_text() for p in (ROOT / "docs" / "cli").glob("*.md")}
    assert set(on_disk) == set(pages), "run scripts/cli_reference.py"
    for name, text in pages.items():
        assert on_disk[name] == text, f"docs/cli/{name} is stale: run scripts/cli_reference.py"


def test_every_command_help_ends_with_an_example() -> None:
    from click.testing import CliRunner

    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    for group, prog in ((jsgs_main, "jsgs"), (tools_main, "jsgstools")):
        for name in group.commands:
            out = CliRunner().invoke(group, [name, "--help"]).output
            tail = out.rstrip().splitlines()[-2:]
            assert tail[0].strip() == "Example:", (name, tail)
            assert tail[1].strip().startswith(f"{prog} {name}"), (name, tail)
