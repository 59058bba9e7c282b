"""The README and the docs: every relative link and image resolves, the README stays a front page.

Checks README.md, CHANGELOG.md and docs/*.md: each relative markdown link or image points at an
existing file (and, with a ``#fragment``, at a heading of that file, by GitHub's slug rule); the
README starts with the two set-up commands, has at most 150 lines and names no path of the
machine it was written on (``../shared``, ``/work/``).
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]

#: ``[text](target)`` and ``![alt](target)``; the target ends at whitespace or ``)``.
_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code (links there are not links)."""
    return _CODE.sub("", _FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = _CODE.sub(lambda m: m.group(0).strip("`"), heading.strip()).lower()
    kept = "".join(c for c in text
                   if c in " -_" or unicodedata.category(c)[0] in "LNM")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The heading anchors of a markdown file (duplicates get GitHub's -1, -2 suffixes)."""
    seen: dict[str, int] = {}
    out = set()
    for line in _FENCE.sub("", path.read_text(encoding="utf-8")).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def relative_links(path: Path) -> list[str]:
    """Relative link and image targets of a markdown file (no URLs, no mailto)."""
    targets = _LINK.findall(_prose(path.read_text(encoding="utf-8")))
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t, re.I)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_image_resolves(page: Path) -> None:
    broken = []
    for target in relative_links(page):
        file_part, _, fragment = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f"{target}: no file {dest}")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            broken.append(f"{target}: no heading #{fragment} in {dest.name}")
    assert not broken, f"{page.name}: " + "; ".join(broken)


def test_the_docs_exist_and_every_page_is_reachable_from_the_readme() -> None:
    names = {p.name for p in PAGES}
    for name in ("README.md", "CHANGELOG.md", "design.md", "results.md", "performance.md",
                 "tuning.md", "capture.md", "viewer.md", "format.md"):
        assert name in names, name
    reached, todo = set(), [ROOT / "README.md"]
    while todo:
        page = todo.pop()
        if page in reached or page.suffix != ".md" or not page.exists():
            continue
        reached.add(page)
        todo += [(page.parent / t.partition("#")[0]).resolve()
                 for t in relative_links(page) if t.partition("#")[0]]
    assert not [p.name for p in PAGES if p not in reached]


def test_readme_is_a_front_page() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    lines = text.splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines (at most 150)"
    assert lines[0] == "```bash"
    assert lines[1].startswith("./run demo") and lines[2].startswith("./run test")
    assert "../shared" not in text
    assert not re.search(r"(/work/|/tmp/|/root/)[A-Za-z]", text)


def test_link_checker_sees_broken_links(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    (tmp_path / "there.md").write_text("# A heading, with `code`\n", encoding="utf-8")
    page.write_text("[ok](there.md#a-heading-with-code) ![img](missing.png) "
                    "[url](https://example.org) `[code](nope.md)`\n"
                    "```\n[fenced](nope.md)\n```\n[bad](there.md#nope)\n", encoding="utf-8")
    assert relative_links(page) == ["there.md#a-heading-with-code", "missing.png",
                                    "there.md#nope"]
    assert anchors(tmp_path / "there.md") == {"a-heading-with-code"}
