"""Output files written whole or not at all (``collect.atomic_files``), and the writers that use it."""

import errno
from pathlib import Path

import pytest

from collect.atomic_files import remove_leftovers, replacing


def _fill_disk_midway(monkeypatch):
    """Path.write_text writes half its text, then fails as a full disk does (naming the file it wrote)."""
    write_text = Path.write_text

    def half_then_enospc(self, text, *args, **kwargs):
        write_text(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", half_then_enospc)


def test_a_failed_write_leaves_the_old_file_and_names_the_target(tmp_path, monkeypatch):
    path = tmp_path / "out.txt"
    path.write_text("old content\n")
    _fill_disk_midway(monkeypatch)
    with pytest.raises(OSError) as err, replacing(path) as tmp:
        tmp.write_text("new content, much longer than the old one\n")
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(path)
    monkeypatch.undo()
    assert path.read_text() == "old content\n" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with replacing(path) as tmp:
        tmp.write_text("new\n")
    assert path.read_text() == "new\n" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_a_report_cut_by_a_full_disk_leaves_the_earlier_report(tmp_path, monkeypatch):
    """Was: report.html written in place, a full disk left a cut-off page that opened like a whole one."""
    from calibrate.report import write_report
    from test_commission_report import _full_report_data

    path = write_report(_full_report_data(True), tmp_path / "report.html")
    before = path.read_bytes()
    _fill_disk_midway(monkeypatch)
    with pytest.raises(OSError, match="No space left") as err:
        write_report(_full_report_data(False), path)
    assert err.value.filename == str(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["report.html"]


def test_a_benchmark_section_cut_by_a_full_disk_leaves_the_earlier_page(tmp_path, monkeypatch):
    """Was: ``update_section`` rewrote the page in place (``Path.write_text``): a full disk or a kill left
    it cut off, the other benchmarks' sections lost with it."""
    from trainer.doc_sections import update_section

    page = tmp_path / "bench_trainer.md"
    update_section(page, "inference", "Inference", ["fps 61"], "# Trainer benchmarks\n")
    update_section(page, "finetune", "Fine-tuning", ["a1 0.97"])
    before = page.read_text()
    _fill_disk_midway(monkeypatch)
    with pytest.raises(OSError, match="No space left"):
        update_section(page, "finetune", "Fine-tuning", ["a1 0.99 " * 50])
    monkeypatch.undo()
    assert page.read_text() == before and [p.name for p in tmp_path.iterdir()] == ["bench_trainer.md"]


def test_leftovers_of_a_killed_writer_are_removed_and_nothing_else(tmp_path):
    (tmp_path / "model").mkdir()
    leftovers = [tmp_path / "acceptance.json.qnn9fi55.tmp", tmp_path / "model" / "model.onnx.a1b2c3d4.tmp"]
    kept = [tmp_path / "notes.tmp", tmp_path / "acceptance.json", tmp_path / "x.ABCDEFGH.tmp", tmp_path / "d.abcdefgh.tmp"]
    kept[-1].mkdir()
    for path in leftovers + kept[:-1]:
        path.write_text("x")
    assert sorted(remove_leftovers(tmp_path)) == sorted(leftovers)
    assert not any(p.exists() for p in leftovers) and all(p.exists() for p in kept)
