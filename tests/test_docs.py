"""The front page and the pages it links to: every relative link resolves, the README stays a front page."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "results" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def relative_links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code blocks are not links
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_relative_link_resolves(page):
    links = relative_links(page)
    missing = [t for t in links if not (page.parent / t.split("#")[0]).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_the_link_checker_sees_links_and_misses(tmp_path):
    page = tmp_path / "p.md"
    (tmp_path / "there.png").write_bytes(b"")
    page.write_text("[a](there.png) ![b](gone.png) [c](https://x.org/y) [d](#top)\n```\n[e](in_code.md)\n```\n")
    assert relative_links(page) == ["there.png", "gone.png"]


def test_the_readme_is_a_front_page():
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 15_000 and len(text.splitlines()) <= 200
    # its two Quickstart commands are the ones CI runs
    assert 'pip install -c constraints.txt -e ".[test]" && pytest' in text
    assert 'pip install -c constraints.txt -e ".[test]" && pytest' in (ROOT / ".ci" / "run").read_text()
    assert "pip install -c constraints.txt -e . && python recipes/sr_dcil_dubins.py" in text
    for page in PAGES:  # no placeholder left by an unfinished edit
        assert not re.search(r"\b[A-Z]+_(TEXT|HEADLINE)\b", page.read_text()), page.name
