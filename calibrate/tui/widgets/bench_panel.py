"""Bench panel: arm, camera and pressure board state from ``BenchSnapshot`` events."""

from __future__ import annotations

import math

import numpy as np
from rich.text import Text
from textual.widgets import Static

from calibrate.commission_events import BenchSnapshot

#: A snapshot older than this (s) while the flow runs marks the bench as stale.
STALE_AFTER_S = 2.0


class BenchPanel(Static):
    """Connection state, mode (sim/real), live TCP pose, wrench and bubble pressure.

    ``arm_state`` is the app's view of the arm (``idle``, ``moving``, ``stopping``, ``stopped``);
    the numbers come from the latest snapshot. Once the link is down (the bench closed, a stop) they
    stay as the last reading, dimmed, and the panel's bottom border says so.
    """

    def __init__(self, simulated: bool, **kwargs) -> None:
        super().__init__(**kwargs)
        self.simulated = simulated
        self.snapshot: BenchSnapshot | None = None
        self.snapshot_age_s: float | None = None
        self.connected = False
        self.arm_state = "idle"
        self.border_title = "Bench"

    def on_mount(self) -> None:
        self._redraw()

    def show(self, snapshot: BenchSnapshot | None, age_s: float | None, connected: bool, arm_state: str) -> None:
        """Update from the latest snapshot (None: keep the last one) and the app's state."""
        if snapshot is not None:
            self.snapshot = snapshot
            self.simulated = snapshot.simulated
        self.snapshot_age_s = age_s
        self.connected = connected
        self.arm_state = arm_state
        self._redraw()

    def _redraw(self) -> None:
        snap = self.snapshot
        mode = Text("SIMULATED", style="bold cyan") if self.simulated else Text("REAL", style="bold yellow")
        if not self.connected:
            link = Text("not connected", style="dim")
        elif self.snapshot_age_s is not None and self.snapshot_age_s > STALE_AFTER_S:
            link = Text(f"stale ({self.snapshot_age_s:.0f} s)", style="bold yellow")
        else:
            link = Text("connected", style="green")
        arm_styles = {"moving": "bold green", "stopping": "bold red", "stopped": "yellow", "idle": "dim"}
        rows: list[tuple[str, Text | str]] = [
            ("mode", mode), ("link", link), ("arm", Text(self.arm_state, style=arm_styles.get(self.arm_state, "")))]
        self.border_subtitle = "last reading" if snap is not None and not self.connected else ""
        if snap is None:
            rows.append(("", Text("no data yet", style="dim")))
        else:
            reading = self._reading_rows(snap)
            if not self.connected:
                reading = [(label, Text(str(value), style="dim")) for label, value in reading]
            rows += reading
        self.update(_two_columns(rows), layout=False)

    @classmethod
    def _reading_rows(cls, snap: BenchSnapshot) -> list[tuple[str, Text | str]]:
        """The snapshot's rows: TCP pose (mm; rotation vector in rad, to 0.01 rad so that the unit fits
        the panel; was: to 0.001 with no unit), force and torque (base frame), bubble pressure, camera."""
        x, y, z, rx, ry, rz = (float(v) for v in snap.tcp_pose)
        rows: list[tuple[str, Text | str]] = [
            ("TCP", f"x {x * 1e3:8.1f} mm"), ("", f"y {y * 1e3:8.1f} mm"), ("", f"z {z * 1e3:8.1f} mm"),
            ("", f"r [{rx:+.2f} {ry:+.2f} {rz:+.2f}] rad")]
        fx, fy, fz, tx, ty, tz = (float(v) for v in snap.wrench)
        force = math.sqrt(fx * fx + fy * fy + fz * fz)
        rows += [("force", f"|F| {force:6.2f} N  Fz {fz:+6.2f}"), ("torque", f"{tx:+.3f} {ty:+.3f} {tz:+.3f} Nm")]
        if math.isfinite(snap.pressure_hpa):
            rows.append(("bubble", f"{snap.pressure_hpa:8.1f} hPa"))
        else:
            rows.append(("bubble", Text("no reading from the board", style="yellow")))
        rows.append(("camera", cls._camera_line(snap)))
        return rows

    @staticmethod
    def _camera_line(snap: BenchSnapshot) -> Text:
        if snap.ir is None and snap.depth_m is None:
            return Text("no frame", style="dim")
        image = snap.depth_m if snap.depth_m is not None else snap.ir
        h, w = np.shape(image)[:2]
        line = Text(f"{w}x{h}")
        if snap.depth_m is not None:
            valid = float(np.count_nonzero(np.asarray(snap.depth_m) > 0)) / max(1, h * w)
            line.append(f"  valid {valid * 100:.0f} %")
        return line


def _two_columns(rows: list[tuple[str, Text | str]]) -> Text:
    """``(label, value)`` rows as two columns, one line each: bold labels padded to the widest and
    a space, then the value, cut with an ellipsis at the panel's edge (plain text, no ``rich`` table
    to measure: the panel is redrawn at every refresh)."""
    width = max(len(label) for label, _ in rows)
    lines = [Text.assemble((label.ljust(width), "bold"), " ", value) for label, value in rows]
    return Text("\n", no_wrap=True, overflow="ellipsis").join(lines)
