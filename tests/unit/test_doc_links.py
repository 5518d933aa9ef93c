"""Every relative link of the README and of the pages under docs/ leads somewhere: the file exists, and an anchor
(``page.md#section``) names a heading of that page (GitHub's rule: lower case, punctuation dropped, spaces to
dashes). The README is the front door and the guides hold the rest, so a moved or renamed page fails here."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lstrip("#").strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(line) for line in text.splitlines() if re.match(r"^#{1,6} ", line)}


def pages() -> list[Path]:
    """README.md and the hand-written pages of docs/ (not the run folders a report copied)."""
    return [REPO / "README.md", *sorted(p for p in (REPO / "docs").rglob("*.md") if "runs" not in p.parts)]


def broken_links(page: Path) -> list[str]:
    problems = []
    for url in LINK.findall(FENCE.sub("", page.read_text())):
        if re.match(r"^[a-z]+:", url):
            continue
        path, _, frag = url.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            problems.append(f"{page.relative_to(REPO)}: no {path}")
        elif frag and target.suffix == ".md" and frag not in anchors(target):
            problems.append(f"{page.relative_to(REPO)}: no section #{frag} in {target.relative_to(REPO)}")
    return problems


def test_every_relative_link_of_the_readme_and_docs_resolves():
    problems = [p for page in pages() for p in broken_links(page)]
    assert not problems, "\n".join(problems)


def test_the_check_finds_a_missing_page_and_a_missing_section(tmp_path):
    (tmp_path / "a.md").write_text("# A page\n\n## Its part\n")
    (tmp_path / "b.md").write_text("[ok](a.md#its-part) [gone](c.md) [no part](a.md#other) [web](https://x.org)\n")
    global REPO
    saved, REPO = REPO, tmp_path
    try:
        assert broken_links(tmp_path / "b.md") == ["b.md: no c.md", "b.md: no section #other in a.md"]
    finally:
        REPO = saved


def test_the_readme_is_a_front_door():
    """At most 250 lines: the rest lives in docs/ (issue 36)."""
    assert len((REPO / "README.md").read_text().splitlines()) <= 250
