"""Shared pytest fixtures. Append new fixtures; don't rewrite others'."""

from __future__ import annotations

import signal
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from collect import session_format as sf


def make_synthetic_session(
    path,
    *,
    objects=("mug", "box"),
    poses_per_object: int = 2,
    frames_per_phase: int = 3,
    n_reference: int = 4,
    height: int = 172,
    width: int = 224,
    simulated: bool = True,
    sensor_serial: str = "SYN-0001",
    seed: int = 0,
) -> Path:
    """Write a small valid session file without the simulator (through the real SessionWriter).

    Camera at the origin looking at a paraboloid dome (apex 93 mm, rim ~123 mm, corners invalid);
    press/hold frames carry a Gaussian dent (2-6 mm deep, pushed towards the camera) at a random
    pixel per pose. Per object: ``n_reference`` free frames (pose_id -1), then for each pose
    ``frames_per_phase`` frames of approach, press, hold, retract. Pose ids run over the session.
    Frames = ``len(objects) * (n_reference + 4 * poses_per_object * frames_per_phase)``.
    Returns ``Path(path)``.
    """
    from collect.session_writer import SessionWriter

    rng = np.random.default_rng(seed)
    fx = fy = 0.5 * width / np.tan(np.radians(35.0))
    intrinsics = {"fx": fx, "fy": fy, "cx": (width - 1) / 2, "cy": (height - 1) / 2, "width": width, "height": height}
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = ((u - intrinsics["cx"]) / (width / 2)) ** 2 + ((v - intrinsics["cy"]) / (height / 2)) ** 2
    rest = (0.093 + 0.03 * np.minimum(r2, 1.0)).astype(np.float32)  # (H,W) float32 m
    fov = r2 < 1.25  # ToF valid field of view
    dots = np.where(rng.random((height, width)) < 0.04, 0.25, 1.0).astype(np.float32)
    vertices = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (0.0, 0.08)], np.float32)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int32)
    object_dicts = [
        {
            "name": name,
            "fixture_pose": [0.4 + 0.15 * i, 0.0, 0.0, 0.0, 0.0, 0.0],
            "mesh_sha256": f"{i:064x}",
            "primitive": {"type": "box", "size": [0.06, 0.06, 0.08]},
            "vertices": vertices,
            "faces": faces,
        }
        for i, name in enumerate(objects)
    ]
    writer = SessionWriter(
        path,
        sensor_serial=sensor_serial,
        sensor_spec={"serial": sensor_serial, "synthetic": True},
        intrinsics=intrinsics,
        camera_in_tcp=[0.0, 0.0, -0.093, 0.0, 0.0, 0.0],
        simulated=simulated,
        objects=object_dicts,
    )
    seq = 0
    pose_id = 0

    def emit(true_depth, object_index, pose, phase, tcp_pose):
        nonlocal seq
        t = seq / 45.0
        noisy = true_depth + rng.normal(0.0, 5e-5, true_depth.shape).astype(np.float32)
        depth = np.where(fov, np.round(noisy / sf.DEPTH_UNIT_M), 0).astype(np.uint16)
        ir = np.clip(20000 * (0.093 / true_depth) ** 2 * dots + rng.normal(0, 100, true_depth.shape), 0, 65535)
        writer.append_frame(ir.astype(np.uint16), depth, t, 1000.0 + t, seq, object_index, pose, phase,
                            tcp_pose, true_depth=true_depth if simulated else None)
        force = 1000.0 * float(rest.max() - true_depth.min()) if phase in (sf.PHASE_PRESS, sf.PHASE_HOLD) else 0.0
        writer.append_arm(1000.0 + t, tcp_pose, [0.0, 0.0, force, 0.0, 0.0, 0.0])
        writer.append_pressure(1000.0 + t, 1065.0 + force)
        seq += 1

    for oi, obj in enumerate(object_dicts):
        above = np.array(obj["fixture_pose"], float) + [0, 0, 0.2, np.pi, 0, 0]
        for _ in range(n_reference):
            emit(rest, oi, -1, sf.PHASE_FREE, above)
        for _ in range(poses_per_object):
            cu, cv = rng.uniform(0.3, 0.7) * width, rng.uniform(0.3, 0.7) * height
            dent = np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * 15.0**2)).astype(np.float32)
            depth_mm = rng.uniform(2.0, 6.0)
            for phase in (sf.PHASE_APPROACH, sf.PHASE_PRESS, sf.PHASE_HOLD, sf.PHASE_RETRACT):
                for k in range(frames_per_phase):
                    frac = {sf.PHASE_APPROACH: 0.0, sf.PHASE_PRESS: (k + 1) / frames_per_phase,
                            sf.PHASE_HOLD: 1.0, sf.PHASE_RETRACT: 0.0}[phase]
                    true = (rest - 1e-3 * depth_mm * frac * dent).astype(np.float32)
                    tcp = above - [0, 0, 0.2 - 0.08 - 1e-3 * depth_mm * frac, 0, 0, 0]
                    emit(true, oi, pose_id, phase, tcp)
            pose_id += 1
    writer.close()
    return Path(path)


@pytest.fixture
def synthetic_session(tmp_path) -> Path:
    """Path of a small simulated session (2 objects 'mug', 'box' x 2 poses, 224x172, 56 frames)."""
    return make_synthetic_session(tmp_path / "synthetic.h5")


@pytest.fixture(name="make_synthetic_session")
def make_synthetic_session_fixture():
    """The ``make_synthetic_session(path, **options)`` factory, for tests that need other shapes."""
    return make_synthetic_session


def interrupt_once_recording(argv: list[str], recording: Path, timeout_s: float = 120.0, signum: int = signal.SIGINT,
                             again_after_s: float | None = None):
    """Run ``bubble ARGV`` in a child, send it ``signum`` (default SIGINT: Ctrl-C) once ``recording``
    holds 2 MB on disk (a few dozen frames; the writer holds HDF5's file lock, so the size is what can
    be watched), and once more ``again_after_s`` later if given; returns ``(returncode, stderr)``.
    SIGINT is restored to its default disposition in the child, as in a terminal, also when pytest was
    started by a shell without job control (which ignores it)."""
    import os
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "calibrate.cli", *argv], cwd=Path(__file__).resolve().parents[1],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None and not (
            recording.exists() and recording.stat().st_size > 2e6):
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[1]
    os.kill(proc.pid, signum)
    if again_after_s is not None:
        time.sleep(again_after_s)
        os.kill(proc.pid, signum)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


def wait_until(predicate, timeout_s: float = 2.0) -> bool:
    """Poll ``predicate()`` every millisecond until it holds (True) or ``timeout_s`` s pass (False):
    for tests that wait on another thread instead of sleeping a guessed time."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.001)
    return True



@pytest.fixture
def interrupt_handlers_restored():
    """The test leaves this process's handlers as it found them (a command's outermost block leaves
    them ignored, for the process's exit)."""
    from collect.stop_signals import INTERRUPTS

    before = {sig: signal.getsignal(sig) for sig in INTERRUPTS}
    yield
    for sig, handler in before.items():
        signal.signal(sig, handler)


def losing_the_first_interrupt(monkeypatch, *modules) -> list[int]:
    """Put in ``modules``' ``raise_interrupt`` (``collect.stop_signals``') one whose first call raises
    nothing, as when Python loses the KeyboardInterrupt that a signal handler raised while a weakref
    callback ran (it only prints "Exception ignored in"); later calls raise. Returns the signal numbers
    it was called with, in order."""
    from collect import stop_signals

    real, calls = stop_signals.raise_interrupt, []

    def lost_the_first_time(signum):
        calls.append(signum)
        if len(calls) > 1:
            real(signum)

    for module in modules:
        monkeypatch.setattr(module, "raise_interrupt", lost_the_first_time)
    return calls


@contextmanager
def ctrl_c_once_it_exists(path: Path, delay_s: float = 0.0):
    """During the with-block, send this process one SIGINT (a Ctrl-C) ``delay_s`` after ``path`` appears,
    from a thread; none when the block ends first."""
    import os
    import threading

    done = threading.Event()

    def operator():
        while not path.exists():
            if done.wait(0.01):
                return
        if not done.wait(delay_s):
            os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=operator)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def disk_only_this_file_fills(monkeypatch, path: Path, disk_bytes: int) -> None:
    """Make the session writer see a disk of ``disk_bytes`` that only ``path`` uses up: its free
    space is ``disk_bytes`` less the file's size (0 before the file exists). Other programs or test
    workers writing to the real disk then cannot move where a free-space limit is crossed."""
    from collect import session_writer

    monkeypatch.setattr(session_writer, "_free_bytes",
                        lambda _: disk_bytes - (path.stat().st_size if path.exists() else 0))
