"""Every citation in the code resolves inside the repository.

Code comments and docstrings cite the pages that hold the knowledge they rely on (``docs/conventions.md,
"The MANO file"``). A reader of the repository has only the repository, so a cited ``.md`` path must exist,
a quoted section after it must be a heading of that page, and nothing may cite the notes that live outside
the repository (the design notes and the reference notes the project was written from).
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("hoidata", "hoisdf", "tests", "bench", "docs", "pipelines", "scripts", ".ci")
SUFFIXES = {".py", ".toml", ".sh", ".md", ""}
PATH = re.compile(r"[\w.-]+(?:/[\w.-]+)+\.md\b")  # a cited markdown path with at least one folder
SECTION = re.compile(r"\b(docs/[\w-]+\.md),\s*#?\s*\"([^\"]+)\"")  # docs/page.md, "Heading"
# The outside notes by name, and section numbers (the docs pages have named sections, so a "§1.14" can only
# point at an outside note's numbering).
OUTSIDE = re.compile(r"\b(?:DESIGN|upstream_hoisdf|upstream_parity|paper_hoisdf|measured_libraries|user_needs|"
                     r"style_anchors|reliability_probe)\.md\b|\breference/[\w-]+\.md\b|§\s*\d")


def _sources() -> dict[str, str]:
    out = {}
    for folder in FOLDERS:
        for path in sorted((ROOT / folder).rglob("*")):
            if path.is_file() and path.suffix in SUFFIXES and "__pycache__" not in path.parts and \
                    path.name != "test_citations.py":
                out[str(path.relative_to(ROOT))] = path.read_text(errors="replace")
    return out


def _headings(page: Path) -> set[str]:
    return {line.lstrip("#").strip().replace("`", "").lower()
            for line in page.read_text().splitlines() if line.startswith("#")}


def _problems(sources: dict[str, str], root: Path) -> list[str]:
    problems = []
    for name, text in sources.items():
        # a page's own paths are often outputs (OUT/table.md); mkdocs --strict checks a page's links
        for cited in sorted(set(PATH.findall(text))) if not name.endswith(".md") else ():
            if not (root / cited).is_file():
                problems.append(f"{name}: cites {cited}, which is not in the repository")
        for page, section in SECTION.findall(text):
            if (root / page).is_file() and section.replace("`", "").lower() not in _headings(root / page):
                problems.append(f'{name}: cites {page}, "{section}", which is no heading of that page')
        if OUTSIDE.search(text):
            problems.append(f"{name}: cites {OUTSIDE.search(text).group(0)}, which lives outside the repository")
    return problems


def test_every_citation_resolves_inside_the_repository():
    problems = _problems(_sources(), ROOT)
    assert not problems, "\n".join(problems)


def test_the_check_finds_each_kind_of_broken_citation(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("# Page\n\n## Units and frames\n")
    sources = {
        "a.py": 'see docs/page.md, "Units and frames" and docs/gone.md',
        "b.py": 'see docs/page.md, "No such heading"',
        "c.py": "as DESIGN.md section 3 says",
        "d.py": "``reference/datasets.md`` section 1",
        "e.py": "upstream initialisation (§1.14)",
    }
    assert _problems(sources, tmp_path) == [
        "a.py: cites docs/gone.md, which is not in the repository",
        'b.py: cites docs/page.md, "No such heading", which is no heading of that page',
        "c.py: cites DESIGN.md, which lives outside the repository",
        "d.py: cites reference/datasets.md, which is not in the repository",
        "d.py: cites reference/datasets.md, which lives outside the repository",
        "e.py: cites §1, which lives outside the repository",
    ]
