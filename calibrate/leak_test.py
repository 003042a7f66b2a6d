"""Bubble leak test: pressure decay of the inflated, untouched bubble over a fixed hold.

The arm holds the sensor still in free air; after a settle time the pressure board is sampled
for ``hold_s`` seconds. The leak rate is the least-squares slope of pressure over time, signed
so that a positive rate is a pressure *loss* (hPa/min). The mean pressure over the hold is the
inflation pressure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from collect.errors import InputError


@dataclass
class LeakTestResult:
    """A recorded hold and its analysis.

    ``t``: ``(P,) float64 s`` since the start of the hold; ``hpa``: ``(P,) float64 hPa`` absolute.
    """

    t: np.ndarray
    hpa: np.ndarray
    rate_hpa_per_min: float  # > 0: pressure loss
    mean_hpa: float
    drop_hpa: float  # fitted pressure at the start minus at the end of the hold
    residual_hpa: float  # RMS of the residuals around the fitted line (sensor noise)
    start_hpa: float  # the fitted line at t = 0

    def fitted_hpa(self) -> np.ndarray:
        """The fitted line at ``t``: ``(P,) float64 hPa``."""
        return self.start_hpa - self.rate_hpa_per_min / 60.0 * self.t

    def summary(self) -> str:
        return f"{self.rate_hpa_per_min:.3f} hPa/min over {self.t[-1] - self.t[0]:.0f} s at {self.mean_hpa:.1f} hPa"

    def to_json(self) -> dict:
        return {
            "rate_hpa_per_min": self.rate_hpa_per_min,
            "mean_hpa": self.mean_hpa,
            "drop_hpa": self.drop_hpa,
            "residual_hpa": self.residual_hpa,
            "hold_s": float(self.t[-1] - self.t[0]),
            "samples": int(self.t.size),
        }


def analyse_leak(t: np.ndarray, hpa: np.ndarray) -> LeakTestResult:
    """Fit the pressure decay of a hold.

    ``t``: ``(P,)`` s (any origin, increasing), ``hpa``: ``(P,)`` hPa absolute, ``P >= 3`` samples
    spanning more than 0 s. Non-finite samples (board glitches) are dropped before the fit.
    """
    t = np.asarray(t, dtype=np.float64).ravel()
    hpa = np.asarray(hpa, dtype=np.float64).ravel()
    if t.shape != hpa.shape:
        raise InputError(f"leak test: {t.size} times but {hpa.size} pressure samples")
    keep = np.isfinite(t) & np.isfinite(hpa)
    t, hpa = t[keep], hpa[keep]
    if t.size < 3 or t[-1] - t[0] <= 0:
        raise InputError(f"leak test: need >= 3 pressure samples over a positive time span, got {t.size}")
    t = t - t[0]
    slope, intercept = np.polyfit(t, hpa, 1)  # hPa/s, hPa
    fit = slope * t + intercept
    return LeakTestResult(
        t=t,
        hpa=hpa,
        rate_hpa_per_min=float(-slope * 60.0),
        mean_hpa=float(hpa.mean()),
        drop_hpa=float(fit[0] - fit[-1]),
        residual_hpa=float(np.sqrt(np.mean((hpa - fit) ** 2))),
        start_hpa=float(intercept),
    )
