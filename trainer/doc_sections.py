"""Replace one marked section of a generated markdown file (benchmark results, model card)."""

from __future__ import annotations

from pathlib import Path

from collect.atomic_files import write_text

#: First lines of docs/bench_trainer.md, whose sections the trainer benchmarks write.
BENCH_TRAINER_HEADER = "# Trainer benchmarks\n\nEach section is written by its benchmark script (rerun it to refresh).\n"


def update_section(path: Path, key: str, title: str, lines: list[str], header: str = "") -> None:
    """Write ``## title`` + ``lines`` between ``<!-- begin:key -->`` / ``<!-- end:key -->`` in ``path``.

    A missing file is started with ``header``; a missing section is appended.
    """
    begin, end = f"<!-- begin:{key} -->", f"<!-- end:{key} -->"
    block = "\n".join([begin, f"## {title}", "", *lines, end])
    text = path.read_text(encoding="utf-8") if path.exists() else header
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    write_text(path, text)
