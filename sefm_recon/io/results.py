"""Keep the generated tables' sections of Markdown files (docs/results.md, README.md) up to date."""

from __future__ import annotations

import os
from pathlib import Path

from .ply import atomic_path

__all__ = ["replace_sections"]


def _markers(section: str) -> tuple[str, str]:
    return f"<!-- eval:{section} begin -->", f"<!-- eval:{section} end -->"


def replace_sections(path: str | os.PathLike, sections: dict[str, str]) -> None:
    """Replace what stands between each section's markers in ``path`` with its text.

    ``sections``: name -> Markdown, the first being the main one. The markers are
    HTML comments (invisible when rendered): ``<!-- eval:NAME begin -->`` and
    ``<!-- eval:NAME end -->``. Sections without markers in the file are skipped,
    except that a file holding none of them gets the main section appended. The
    file is replaced atomically.
    """
    path = Path(path)
    text = path.read_text() if path.exists() else ""
    found = False
    for name, body in sections.items():
        begin, end = _markers(name)
        if begin in text and end in text.split(begin, 1)[1]:
            head, rest = text.split(begin, 1)
            text = f"{head}{begin}\n{body.rstrip()}\n{end}{rest.split(end, 1)[1]}"
            found = True
    if not found:
        name, body = next(iter(sections.items()))
        begin, end = _markers(name)
        text = (text.rstrip() + "\n\n" if text.strip() else "") + f"{begin}\n{body.rstrip()}\n{end}\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text)
