"""Every relative link in the README and docs/ points at a file that exists, and every `#anchor` at a heading of
the page it names (GitHub's heading slugs: lower case, punctuation dropped, spaces to hyphens, a repeated
heading numbered)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def heading_slugs(text: str) -> set[str]:
    """The anchors GitHub gives the page's headings (fenced code blocks left out)."""
    out, seen, fenced = set(), {}, False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        m = None if fenced else re.match(r"^#{1,6}\s+(.*)$", line)
        if m is None:
            continue
        slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def test_slugs_follow_githubs_rule():
    text = "# A `--flag`, on by default\n```\n# not a heading\n```\n## Two\n## Two\n### The cloth's joint (m = 1)\n"
    assert heading_slugs(text) == {"a---flag-on-by-default", "two", "two-1", "the-cloths-joint-m--1"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_resolve(page):
    bad = []
    for m in re.finditer(r"\]\(([^)\s]+)\)", page.read_text()):
        target = m.group(1)
        if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = page if not path else page.parent / path
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in heading_slugs(dest.read_text()):
            bad.append(f"{target}: no such heading")
    assert not bad, f"{page.name}: " + "; ".join(bad)
