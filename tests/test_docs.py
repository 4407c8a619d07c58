"""The README and docs/: every relative link resolves, the README stays a five-minute read."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_CODE = re.compile(r"```.*?```|`[^`\n]*`", re.DOTALL)


def _prose(text: str) -> str:
    """The text without code: fenced blocks, indented blocks and `spans` (their brackets are not links)."""
    text = _CODE.sub("", text)
    return "\n".join(line for line in text.splitlines() if not line.startswith("    "))


def _anchors(path: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces as hyphens."""
    heads = re.findall(r"^#{1,6}\s+(.+?)\s*$", _CODE.sub(lambda m: m.group(0).strip("`"), path.read_text()),
                       re.MULTILINE)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in heads}


def broken_links(path: Path) -> list[str]:
    """Relative links of a Markdown file whose file (or heading anchor) does not exist."""
    bad = []
    for target in _LINK.findall(_prose(path.read_text())):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        name, _, anchor = target.partition("#")
        dest = (path.parent / name).resolve() if name else path
        if not dest.exists():
            bad.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(target)
    return bad


@pytest.mark.parametrize("path", DOCS, ids=[p.relative_to(ROOT).as_posix() for p in DOCS])
def test_every_relative_link_resolves(path):
    assert broken_links(path) == []


def test_the_link_check_finds_missing_files_and_anchors(tmp_path):
    (tmp_path / "other.md").write_text("# Title\n\n## Large photos\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md) [ok](other.md#large-photos) [gone](missing.md) [bad](other.md#small-photos)\n"
                    "![img](pic.png) [web](https://example.org/x) `[code](nowhere.md)`\n\n    [x](indented.md)\n")
    assert broken_links(page) == ["missing.md", "other.md#small-photos", "pic.png"]


def test_the_readme_is_short_and_says_how_to_start():
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 15_000
    for needed in ("make demo", "sefm-recon pair", "sefm-recon colmap", "MeshLab", "colmap gui", "Errors and limits",
                   "<!-- eval:readme begin -->", "<!-- eval:readme end -->", "arXiv:1812.02925"):
        assert needed in text, needed


@pytest.mark.parametrize("path", DOCS, ids=[p.relative_to(ROOT).as_posix() for p in DOCS])
def test_no_development_diary(path):
    """The docs describe what is, not the order it was written in."""
    diary = re.compile(r"\b(this session|earlier (?:version|run|session)s?|used to be|before this version|"
                       r"(?:\w+ )?(?:sessions?|commits?) ago|we now|is now|are now|now (?:runs|gives|uses))\b", re.I)
    assert diary.findall(path.read_text()) == []


def _sections(text: str) -> list[str]:
    return re.split(r"^#{2,3} ", text, flags=re.MULTILINE)


def test_every_results_table_stands_under_its_command():
    """A table or printed block in docs/results.md shares its section with the command that regenerates it."""
    text = (ROOT / "docs" / "results.md").read_text()
    checked = 0
    for section in _sections(text)[1:]:
        if "\n|---" in section or "\n```" in section:
            checked += 1
            commands = [line for line in section.splitlines()
                        if line.startswith("    ") and re.search(r"\.venv/bin/|scripts/|\bmake ", line)]
            assert commands, section.splitlines()[0]
    assert checked >= 5  # real, generated, the DP's, speed and memory, workspaces
