"""Membrane mechanics of an air-filled bubble: an obstacle problem coupled to the gas law.

Unknown: ``u (rows,cols) m``, the change of z-depth of the membrane along each camera ray of the
physics grid (positive = away from the camera, i.e. bulging out). Linearized about the inflated
rest state, a tension-dominated curved membrane obeys, off contact,

    T * lap(u) - k * u = -dp                              (Pa)

with ``T`` the effective membrane tension (N/m), ``k`` the stretching stiffness of the curved
dome (Pa/m; ``k = 0`` gives the pure tension membrane ``T lap u = -dp``; ``k > 0`` localizes a
dent over ``sqrt(T/k)``, as on a real inflated dome) and ``dp`` the pressure rise over the rest
pressure. ``u = 0`` at the clamped rim. The object may not be penetrated: ``u <= psi`` where
``psi`` is the object's depth along the ray minus the rest depth; on the contact set (found by
the solver, not imposed) the object pushes inward with the pressure ``T lap u - k u + dp >= 0``.

The Laplacian is taken on the pixel grid with the physical pixel spacing at the rest depth,
``depth/f``. The pressure follows the isothermal gas law ``P (V0 + dV) = K(t)`` with ``dV`` the
volume swept by ``u`` and ``K`` the gas content (constant, or decaying for a leaking bubble).

Solution method: ``u = w + dp * b`` where ``b`` is the response to a unit pressure rise (one
sparse solve per sensor) and ``w`` solves the homogeneous obstacle problem with the obstacle
``psi - dp*b``: projected SOR (red-black), warm-started from the previous solve, with ``dp``
updated from the gas law between sweeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: Over-relaxation factor of the projected SOR sweeps.
OMEGA = 1.8
#: Convergence: largest change of ``w`` in one sweep (m).
TOLERANCE_M = 1e-6
MAX_SWEEPS = 600
#: A pixel is in contact when the membrane is this close to the obstacle (m).
CONTACT_TOLERANCE_M = 2e-6
CHECK_EVERY = 4


@dataclass
class MembraneSolution:
    """Result on the physics grid (all ``(rows,cols)`` arrays float64)."""

    u: np.ndarray  # m, depth change along the rays
    w: np.ndarray  # m, the contact-driven part of u
    contact: np.ndarray  # bool
    load_n: np.ndarray  # N, inward force of the object on each contact pixel (0 elsewhere)
    pressure_pa: float  # absolute
    dent_volume_m3: float  # volume pushed in by the object (>= 0)
    net_volume_change_m3: float  # total change of the enclosed volume
    sweeps: int


class MembraneSolver:
    """Obstacle problem on a masked grid.

    ``rest_depth (rows,cols) m`` (only used inside ``mask``), ``mask (rows,cols) bool`` free
    membrane pixels, ``fx, fy``: focal lengths of the grid in grid pixels. Mechanics and air
    from the spec: ``tension`` N/m, ``stiffness`` Pa/m, ``gas_volume`` m^3, ``rest_pressure`` Pa.
    """

    def __init__(self, rest_depth, mask, fx, fy, tension, stiffness, gas_volume, rest_pressure):
        self.shape = rest_depth.shape
        rows, cols = self.shape
        self.mask = np.asarray(mask, dtype=bool).copy()
        self.mask[0, :] = self.mask[-1, :] = self.mask[:, 0] = self.mask[:, -1] = False  # rim outside
        d = np.where(self.mask, rest_depth, 1.0)
        self.tension = float(tension)
        self.stiffness = float(stiffness)
        self.gas_volume = float(gas_volume)
        self.rest_pressure = float(rest_pressure)
        self.ax = self.tension * (fx / d) ** 2  # Pa/m per unit second difference along x
        self.ay = self.tension * (fy / d) ** 2
        self.area = d**2 / (fx * fy)  # m^2 of membrane (projected normal to the axis) per pixel
        self.area[~self.mask] = 0.0

        # Flat indexing into the zero-padded array (rows+2, cols+2).
        pcols = cols + 2
        self._pshape = (rows + 2, cols + 2)
        ii, jj = np.nonzero(self.mask)
        flat = (ii + 1) * pcols + (jj + 1)
        den = 2 * self.ax[ii, jj] + 2 * self.ay[ii, jj] + self.stiffness
        self._colors = []
        for color in (0, 1):
            sel = (ii + jj) % 2 == color
            f = flat[sel]
            self._colors.append(
                (
                    f,
                    f + 1,
                    f - 1,
                    f + pcols,
                    f - pcols,
                    self.ax[ii[sel], jj[sel]] / den[sel],
                    self.ay[ii[sel], jj[sel]] / den[sel],
                    np.nonzero(sel)[0],
                )
            )
        self._ii, self._jj, self._flat = ii, jj, flat
        self._poisson = None
        self.unit_response = self._solve_unit_pressure()  # b: m per Pa
        self.unit_volume = float((self.unit_response * self.area).sum())  # m^3 per Pa
        self._w = np.zeros(self._pshape).ravel()
        self._w_prev = self._w.copy()

    # ---- setup ---------------------------------------------------------------------------------
    def _operator(self, stiffness: float) -> sp.csc_matrix:
        """Sparse ``-(T lap) + stiffness`` on the free pixels (Pa/m), Dirichlet 0 outside the mask."""
        ii, jj = self._ii, self._jj
        n = len(ii)
        index = -np.ones(self.shape, dtype=np.int64)
        index[ii, jj] = np.arange(n)
        ax, ay = self.ax[ii, jj], self.ay[ii, jj]
        rows, cols, vals = [np.arange(n)], [np.arange(n)], [2 * ax + 2 * ay + stiffness]
        for di, dj, coef in ((0, 1, ax), (0, -1, ax), (1, 0, ay), (-1, 0, ay)):
            nb = index[ii + di, jj + dj]
            ok = nb >= 0
            rows.append(np.arange(n)[ok])
            cols.append(nb[ok])
            vals.append(-coef[ok])
        return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))

    def _solve_unit_pressure(self) -> np.ndarray:
        """``b``: solution of ``T lap b - k b = -1`` (1 Pa pressure rise), 0 at the rim."""
        b = np.zeros(self.shape)
        b[self._ii, self._jj] = spla.spsolve(self._operator(self.stiffness), np.ones(len(self._ii)))
        return b

    def poisson(self, source: np.ndarray) -> np.ndarray:
        """``phi (rows,cols)`` with ``lap(phi) = source`` (physical units, ``source`` per m^2 times
        m^2 -> m^2) on the free pixels, 0 at the rim; the factorization is built on first use."""
        if self._poisson is None:
            self._poisson = spla.factorized(self._operator(0.0) / self.tension)
        phi = np.zeros(self.shape)
        phi[self._ii, self._jj] = -self._poisson(np.ascontiguousarray(source[self._ii, self._jj], dtype=np.float64))
        return phi

    # ---- solve ---------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the warm start."""
        self._w[:] = 0.0
        self._w_prev[:] = 0.0

    def pressure_for(self, contact_volume: float, gas_content: float) -> float:
        """Absolute pressure (Pa) from ``P (V0 + Vw + (P - P0) Vb) = K``."""
        vb, p0 = self.unit_volume, self.rest_pressure
        qa = vb
        qb = self.gas_volume + contact_volume - p0 * vb
        return float((-qb + np.sqrt(qb * qb + 4 * qa * gas_content)) / (2 * qa))

    def solve(self, psi: np.ndarray, gas_content: float, extrapolate: bool = False) -> MembraneSolution:
        """Solve for obstacle ``psi (rows,cols) m`` (``inf`` = nothing along the ray) and gas
        content ``gas_content`` (Pa m^3, ``rest_pressure * gas_volume`` for a sealed bubble).

        Starts from the previous solution; ``extrapolate`` starts from its linear extrapolation
        from the last two solves instead (for an obstacle moving steadily, e.g. a pressing arm)."""
        ii, jj = self._ii, self._jj
        b_in = self.unit_response[ii, jj]
        psi_in = np.asarray(psi, dtype=np.float64)[ii, jj]
        area_in = self.area[ii, jj]
        w = self._w
        previous = w.copy()
        if extrapolate:
            w += w - self._w_prev
        self._w_prev = previous
        pressure = self.pressure_for(float((w[self._flat] * area_in).sum()), gas_content)
        sweeps = 0
        if np.all(psi_in - (pressure - self.rest_pressure) * b_in >= 0.0):
            w[:] = 0.0  # nothing reaches the membrane: w = 0 is the exact solution
            pressure = self.pressure_for(0.0, gas_content)
        else:
            for sweeps in range(1, MAX_SWEEPS + 1):
                phi = psi_in - (pressure - self.rest_pressure) * b_in
                change = 0.0
                for idx, e, wst, s, n, cx, cy, sel in self._colors:
                    old = w[idx]
                    new = old + OMEGA * (cx * (w[e] + w[wst]) + cy * (w[s] + w[n]) - old)
                    np.minimum(new, phi[sel], out=new)
                    w[idx] = new
                    if sweeps % CHECK_EVERY == 0:
                        change = max(change, float(np.abs(new - old).max()))
                pressure = self.pressure_for(float((w[self._flat] * area_in).sum()), gas_content)
                if sweeps % CHECK_EVERY == 0 and change < TOLERANCE_M:
                    break
        phi_grid = np.where(
            self.mask, np.asarray(psi, dtype=np.float64) - (pressure - self.rest_pressure) * self.unit_response, np.inf
        )
        wp = w.reshape(self._pshape)
        np.minimum(wp[1:-1, 1:-1], phi_grid, out=wp[1:-1, 1:-1])  # final projection
        wg = wp[1:-1, 1:-1].copy()
        pressure = self.pressure_for(float((wg * self.area).sum()), gas_content)  # exact gas law for w
        dp = pressure - self.rest_pressure
        u = wg + dp * self.unit_response
        contact = self.mask & (wg >= phi_grid - CONTACT_TOLERANCE_M)
        load = self._contact_load(wp, contact)
        dent = -float((wg * self.area).sum())
        net = float((u * self.area).sum())
        return MembraneSolution(u, wg, contact, load, pressure, dent, net, sweeps)

    def _contact_load(self, wp: np.ndarray, contact: np.ndarray) -> np.ndarray:
        """Inward object force per contact pixel, ``(T lap w - k w) * area`` (N), clipped at 0."""
        c = wp[1:-1, 1:-1]
        lap_x = wp[1:-1, 2:] + wp[1:-1, :-2] - 2 * c
        lap_y = wp[2:, 1:-1] + wp[:-2, 1:-1] - 2 * c
        pressure = self.ax * lap_x + self.ay * lap_y - self.stiffness * c
        return np.where(contact, np.maximum(pressure, 0.0) * self.area, 0.0)
