"""Shared by the trainer benchmarks: replace one marked section of a markdown results file."""

from __future__ import annotations

from pathlib import Path

HEADER = "# Trainer benchmarks\n\nEach section is written by its benchmark script (rerun it to refresh).\n"


def update_section(path: Path, key: str, title: str, lines: list[str]) -> None:
    """Write ``## title`` + ``lines`` between ``<!-- begin:key -->`` / ``<!-- end:key -->`` in ``path``."""
    begin, end = f"<!-- begin:{key} -->", f"<!-- end:{key} -->"
    block = "\n".join([begin, f"## {title}", "", *lines, end])
    text = path.read_text() if path.exists() else HEADER
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text)
