"""Native driver libraries' own console lines are held back while a device connects and folded into
the one-line fault (``collect.native_output``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from collect.camera import DepthaiToFCamera
from collect.errors import HardwareFault
from collect.native_output import folded, native_output_into


def test_what_native_code_writes_is_held_back_and_passed_on_only_after_success(capfd):
    lines: list[str] = []
    with pytest.raises(RuntimeError):
        with native_output_into(lines):
            os.write(1, b"[2026-11-24 00:41:39.693] [host] [error] Searched, but no device found\n")
            os.write(2, b"connect: Connection refused\n\n")
            raise RuntimeError("cannot connect")
    assert lines == ["[host] [error] Searched, but no device found", "connect: Connection refused"]
    assert capfd.readouterr() == ("", "")  # nothing reached the console
    assert folded(lines) == " ([host] [error] Searched, but no device found; connect: Connection refused)"
    assert folded([]) == ""

    lines = []
    with native_output_into(lines):
        os.write(1, b"uploaded\n")
        os.write(2, b"note\n")
    assert lines == ["uploaded", "note"]
    assert capfd.readouterr() == ("uploaded\n", "note\n")  # after success, each on its own descriptor


def test_an_oak_camera_that_cannot_be_found_is_one_fault_line(capfd, monkeypatch):
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "300")  # ms; depthai searches 10 s by default
    with pytest.raises(HardwareFault) as err:
        DepthaiToFCamera(device_id="127.0.0.1").start()
    assert err.value.kind == "camera-missing"
    assert str(err.value).startswith("camera: cannot open the OAK ToF device: ")
    assert "\n" not in str(err.value)
    assert capfd.readouterr() == ("", "")  # depthai's own log lines are in the message, not on the console


def test_a_bad_real_bench_file_is_one_line_in_a_fresh_process_where_importing_depthai_warns(tmp_path):
    """In a container without /dev/bus/usb, ``import depthai`` prints "USB protocol not available";
    a bench file's ToF profile is checked with depthai, so that warning came first on stdout, before
    the error line of a bench file with no robot_ip (a fresh process: depthai not imported yet)."""
    bench = tmp_path / "bench.yaml"
    bench.write_text("type: ur\nobjects: [mug]\n")
    env = {k: v for k, v in os.environ.items() if k != "DEPTHAI_LEVEL"}  # the twin quiets depthai; no twin here
    run = subprocess.run([sys.executable, "-m", "calibrate.cli", "collect", "--bench", str(bench), "--out",
                          str(tmp_path / "s.h5")], capture_output=True, text=True, env=env, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert (run.returncode, run.stdout, run.stderr) == (2, "", "bubble: error: bench 'ur': robot_ip is required\n")
