"""docs/ as a reader walks it: every page reachable from docs/index.md by links, and every
relative link in docs/ and README.md pointing at a file that exists (and, with a
#fragment into a Markdown page, at one of its headings)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
INDEX = DOCS / "index.md"

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.DOTALL | re.MULTILINE)


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of a Markdown page's headings."""
    text = FENCE.sub("", page.read_text())
    out: set[str] = set()
    seen: dict[str, int] = {}
    for m in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", text, re.MULTILINE):
        slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(page: Path) -> list[tuple[str, Path | None, str]]:
    """(target as written, the file it names or None when external, fragment)."""
    text = FENCE.sub("", page.read_text())
    text = re.sub(r"`[^`\n]*`", "", text)  # inline code is not a link
    out = []
    for m in LINK.finditer(text):
        target = m.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            out.append((target, None, ""))
            continue
        name, _, fragment = target.partition("#")
        path = page if not name else (page.parent / name).resolve()
        out.append((target, path, fragment))
    return out


def pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def broken(page: Path) -> list[str]:
    bad = []
    for target, path, fragment in links(page):
        if path is None:
            continue
        real = path
        if not real.exists():
            bad.append(f"{target} (no {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path})")
        elif fragment and real.suffix == ".md" and fragment not in anchors(real):
            bad.append(f"{target} (no heading #{fragment} in {real.relative_to(ROOT)})")
    return bad


def reachable(start: Path) -> set[Path]:
    seen, todo = set(), [start]
    while todo:
        page = todo.pop()
        if page in seen:
            continue
        seen.add(page)
        for _, path, _ in links(page):
            if path is not None and path.suffix == ".md":
                real = path
                if real.exists() and real.is_relative_to(DOCS):
                    todo.append(real)
    return seen


@pytest.mark.parametrize("page", [ROOT / "README.md", *pages()], ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert broken(page) == []


def test_every_page_is_reachable_from_the_index():
    assert INDEX.exists()
    unreached = [str(p.relative_to(ROOT)) for p in pages() if p not in reachable(INDEX)]
    assert unreached == []


def test_readme_points_into_the_index():
    assert any(path == INDEX for _, path, _ in links(ROOT / "README.md"))


def test_the_checks_can_fail(tmp_path):
    """A broken link, a missing heading and an orphan page are each found."""
    docs = tmp_path / "docs"
    (docs / "guide").mkdir(parents=True)
    (docs / "index.md").write_text(
        "# Index\n\n[guide](guide/a.md) [gone](guide/gone.md)\n"
        "[bad anchor](guide/a.md#nowhere) [good](guide/a.md#a-page)\n"
    )
    (docs / "guide" / "a.md").write_text("# A page\n\n```\n[not a link](x.md)\n```\n")
    (docs / "guide" / "orphan.md").write_text("# Nobody links here\n")
    global DOCS, ROOT
    saved = DOCS, ROOT
    DOCS, ROOT = docs, tmp_path
    try:
        assert broken(docs / "index.md") == [
            "guide/gone.md (no docs/guide/gone.md)",
            "guide/a.md#nowhere (no heading #nowhere in docs/guide/a.md)",
        ]
        assert broken(docs / "guide" / "a.md") == []
        assert docs / "guide" / "orphan.md" not in reachable(docs / "index.md")
        assert docs / "guide" / "a.md" in reachable(docs / "index.md")
    finally:
        DOCS, ROOT = saved


def test_the_cli_reference_names_every_command_and_option():
    import argparse

    from ftsensord.cli import build_parser

    page = (DOCS / "reference" / "cli.md").read_text()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name, parser in sub.choices.items():
        section = page.partition(f"\n## ftsensord {name}\n")[2].partition("\n## ")[0]
        if not section:
            missing.append(name)
        for action in parser._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help") and f"`{option}`" not in section:
                    missing.append(f"{name} {option}")
    assert missing == []
