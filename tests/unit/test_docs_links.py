"""The documentation stands alone and its links resolve.

Checked on README.md and every docs/*.md:
- every relative Markdown link `[text](target)` and image `![alt](target)` names a file or folder that exists
  (the `#anchor` part is not checked; links with a scheme, `http:`, `https:`, `mailto:`, and pure `#anchor`
  links are skipped);
- every page path written out in the text (`docs/NAME.md`) exists;
- docs/index.md links every page of docs/;
- nothing cites the workspace's shared folder (the repository must stand alone);
- no page but docs/performance.md carries a benchmark journal: the marks of one (a load average, ns per step,
  CPU seconds, medians of so many runs) appear nowhere else;
- README.md stays a front door: at most 6 KiB (6144 bytes).

Fenced code blocks and inline code spans are masked before links are looked for, so that Python such as
`run.to_xarray()["clsf"](...)` is not read as a link.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
README_MAX_BYTES = 6144

PAGES = [README, *sorted(DOCS.glob("*.md"))]
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
PAGE_PATH = re.compile(r"(?<![\w./-])docs/[\w.-]+\.md\b")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")
PERFORMANCE = DOCS / "performance.md"
JOURNAL_MARKS = re.compile(
    r"load average|1-minute load|\d ?ns ?(?:/|per) ?step|\d CPU s\b"
    r"|medians? of \d+ (?:runs|alternating|processes|rounds)",
    re.IGNORECASE,
)


def _prose(text: str) -> str:
    """The text with fenced blocks and code spans blanked (links inside code are not links)."""
    text = FENCE.sub("", text)
    return CODE_SPAN.sub("code", text)


def relative_link_targets(text: str) -> list[str]:
    """The file part of every relative link in Markdown text, in order (anchors and query strings cut)."""
    targets = []
    for match in LINK.finditer(_prose(text)):
        target = match.group(1)
        if SCHEME.match(target) or target.startswith("#"):
            continue
        target = target.split("#", 1)[0].split("?", 1)[0]
        if target:
            targets.append(target)
    return targets


def _name(page: Path) -> str:
    return page.relative_to(ROOT).as_posix()


def test_the_pages_are_found() -> None:
    assert README.is_file()
    assert len(PAGES) > 10, f"expected README.md and the docs/ pages, found {[_name(p) for p in PAGES]}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_every_relative_link_resolves(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    missing = [t for t in relative_link_targets(text) if not (page.parent / t).exists()]
    assert not missing, f"{_name(page)} links to files that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_every_page_path_named_in_the_text_exists(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    missing = sorted({p for p in PAGE_PATH.findall(text) if not (ROOT / p).is_file()})
    assert not missing, f"{_name(page)} names pages that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_no_page_cites_the_shared_workspace(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    for cited in ("../shared", "/work/shared"):
        assert cited not in text, f"{_name(page)} cites {cited}: the repository must stand alone"


@pytest.mark.parametrize("page", [p for p in PAGES if p != PERFORMANCE], ids=_name)
def test_measurement_journals_live_only_in_performance_md(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    marks = [m.group(0) for m in JOURNAL_MARKS.finditer(text)]
    assert not marks, f"{_name(page)} carries measured speed figures ({marks}): they belong in docs/performance.md"


def test_performance_md_carries_the_journals() -> None:
    assert JOURNAL_MARKS.search(PERFORMANCE.read_text(encoding="utf-8")), "the journal marks no longer match anything"


def test_the_index_links_every_page() -> None:
    linked = {(DOCS / t).resolve() for t in relative_link_targets((DOCS / "index.md").read_text(encoding="utf-8"))}
    unlisted = [p.name for p in PAGES[1:] if p.name != "index.md" and p.resolve() not in linked]
    assert not unlisted, f"docs/index.md does not list {unlisted}"


def test_readme_is_a_front_door() -> None:
    size = len(README.read_bytes())
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes, more than {README_MAX_BYTES}: move detail to docs/"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("see [the file](docs/hdf5.md) and ![fig](figures/a.png)", ["docs/hdf5.md", "figures/a.png"]),
        ("[a section](clsf.md#what-it-costs), [here](#top), [web](https://example.org/x.md)", ["clsf.md"]),
        ('[titled](wiring.md "the cables") [spaced]( cli.md )', ["wiring.md", "cli.md"]),
        ('`tree["clsf"](x)` and\n```\n[not](a-link.md)\n```\n[real](real.md)', ["real.md"]),
    ],
)
def test_link_extraction(text: str, expected: list[str]) -> None:
    assert relative_link_targets(text) == expected
