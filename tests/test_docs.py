"""Every citation in the code resolves to the repository's docs/: `formats.md §N.M`,
`algorithms.md §N.M` (and `§7 (a)`), `architecture.md "Section"`, and every paper equation
label `eq:…` is listed in docs/paper_map.md."""

from __future__ import annotations

import re

import pytest

from helpers import REPOSITORY

DOCS = REPOSITORY / "docs"
CODE = sorted((REPOSITORY / "rotonly_cli").rglob("*.py")) + sorted((REPOSITORY / "scripts").rglob("*.py"))


def _citations(pattern: str) -> set[tuple[str, str]]:
    found = set()
    for path in CODE:
        for match in re.finditer(pattern, path.read_text()):
            found.add((str(path.relative_to(REPOSITORY)), match.group(1)))
    return found


def _sections(document: str) -> set[str]:
    """Section numbers of a doc's headings: "## 4." -> "4", "### 4.7 ..." -> "4.7"."""
    return {m.group(1) for m in re.finditer(r"^#{2,3} (\d+(?:\.\d+)?)\.?\s", document, re.M)}


@pytest.mark.parametrize("name", ["formats", "algorithms"])
def test_section_citations_resolve(name):
    document = (DOCS / f"{name}.md").read_text()
    sections = _sections(document)
    cited = _citations(rf"{name}\.md §(\d+(?:\.\d+)?)")
    assert cited, f"no citation of {name}.md found"
    missing = sorted((path, section) for path, section in cited if section not in sections)
    assert not missing, f"{name}.md lacks the sections {missing}"


def test_lettered_subsections_resolve():
    document = (DOCS / "algorithms.md").read_text()
    section_7 = document[document.index("## 7."):]
    for path, letter in _citations(r"algorithms\.md §7 \(([a-z])\)"):
        assert f"**({letter})" in section_7, (path, letter)


def test_architecture_citations_resolve():
    headings = set(re.findall(r"^#{2,3} (.+?)\s*$", (DOCS / "architecture.md").read_text(), re.M))
    for path, title in _citations(r'architecture\.md "([^"]+)"'):
        assert title in headings, f'{path} cites architecture.md "{title}"'


def test_every_cited_equation_is_in_the_paper_map():
    paper_map = (DOCS / "paper_map.md").read_text()
    listed = set(re.findall(r"`eq:([A-Za-z0-9_-]+)`", paper_map))
    cited = {label for _, label in _citations(r"eq:([A-Za-z0-9_-]*[A-Za-z0-9_])")}
    assert cited and not cited - listed, sorted(cited - listed)


def test_readme_links_resolve_and_readme_is_short():
    readme = (REPOSITORY / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    wide = [(number, len(line)) for number, line in enumerate(readme.splitlines(), 1) if len(line) > 120]
    assert not wide, f"README lines over 120 columns: {wide}"
    for target in re.findall(r"\]\(((?:docs/)?[\w./-]+\.(?:md|png))\)", readme):
        assert (REPOSITORY / target).is_file(), target
