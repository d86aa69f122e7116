"""Conductors and line constants of the embedded rural feeder (Kersting, *Distribution System Modeling and
Analysis*, ch. 4-5): the overhead conductors, the modified Carson impedance and the potential-coefficient
capacitance of a pole-top geometry with the neutral Kron-reduced, and the four line codes the generator writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CONDUCTORS",
    "LINECODES",
    "Conductor",
    "LineCode",
    "phase_capacitance_uf_per_mile",
    "phase_impedance_ohm_per_mile",
]

_KM_PER_MILE = 1.609344


@dataclass(frozen=True)
class Conductor:
    """An overhead conductor.

    Resistance at 50 degC, 60 Hz [ohm/mile], GMR [ft], outside diameter [in], ampacity [A].
    """

    r_ohm_per_mile: float
    gmr_ft: float
    diameter_in: float
    ampacity_a: float


#: Conductor data as tabulated in Kersting, Appendix B.
CONDUCTORS: dict[str, Conductor] = {
    "336_acsr": Conductor(0.306, 0.0244, 0.721, 530.0),
    "4/0_acsr": Conductor(0.592, 0.00814, 0.563, 340.0),
    "1/0_acsr": Conductor(1.12, 0.00446, 0.398, 230.0),
    "2_acsr": Conductor(1.69, 0.00418, 0.316, 180.0),
    "4_acsr": Conductor(2.55, 0.00452, 0.257, 140.0),
}


def _distances_ft(xy_ft: np.ndarray) -> np.ndarray:
    diff = xy_ft[:, None, :] - xy_ft[None, :, :]
    return np.hypot(diff[..., 0], diff[..., 1])


def _kron_reduce(m: np.ndarray, n_phases: int) -> np.ndarray:
    a, b = m[:n_phases, :n_phases], m[:n_phases, n_phases:]
    c, d = m[n_phases:, :n_phases], m[n_phases:, n_phases:]
    return a - b @ np.linalg.solve(d, c)


def phase_impedance_ohm_per_mile(
    xy_ft: np.ndarray, r_ohm_per_mile: np.ndarray, gmr_ft: np.ndarray, n_phases: int
) -> np.ndarray:
    """Phase impedance matrix of an overhead line with its neutral(s) Kron-reduced [ohm/mile].

    Modified Carson equations at 60 Hz and an earth resistivity of 100 ohm-m (Kersting eq. 4.41-4.42):
    ``z_ii = r_i + 0.09530 + j 0.12134 (ln(1/GMR_i) + 7.93402)``,
    ``z_ij = 0.09530 + j 0.12134 (ln(1/D_ij) + 7.93402)``, then Kron reduction (eq. 4.56).

    Parameters
    ----------
    xy_ft : (n, 2) conductor positions (horizontal, height above ground) [ft]; phases first.
    r_ohm_per_mile, gmr_ft : (n,) conductor resistance [ohm/mile] and geometric mean radius [ft].
    n_phases : number of phase conductors (the rest are neutrals).

    Returns
    -------
    (n_phases, n_phases) complex impedance matrix [ohm/mile].
    """
    d = _distances_ft(np.asarray(xy_ft, dtype=float))
    np.fill_diagonal(d, np.asarray(gmr_ft, dtype=float))
    z = 0.09530 + 1j * 0.12134 * (np.log(1.0 / d) + 7.93402)
    z = z + np.diag(np.asarray(r_ohm_per_mile, dtype=float))
    return _kron_reduce(z, n_phases)


def phase_capacitance_uf_per_mile(xy_ft: np.ndarray, diameter_in: np.ndarray, n_phases: int) -> np.ndarray:
    """Shunt capacitance matrix of an overhead line with grounded neutral(s) [uF/mile].

    Potential coefficients with conductor images (Kersting eq. 5.9-5.10):
    ``P_ii = 11.17689 ln(S_ii / RD_i)``, ``P_ij = 11.17689 ln(S_ij / D_ij)`` [mile/uF], Kron-reduced,
    then ``C = P^-1``.

    Parameters
    ----------
    xy_ft : (n, 2) conductor positions (horizontal, height above ground) [ft]; phases first.
    diameter_in : (n,) conductor outside diameters [in].
    n_phases : number of phase conductors.

    Returns
    -------
    (n_phases, n_phases) capacitance matrix [uF/mile].
    """
    xy = np.asarray(xy_ft, dtype=float)
    image = xy * np.array([1.0, -1.0])
    diff = xy[:, None, :] - image[None, :, :]
    s = np.hypot(diff[..., 0], diff[..., 1])
    d = _distances_ft(xy)
    np.fill_diagonal(d, np.asarray(diameter_in, dtype=float) / 24.0)
    p = 11.17689 * np.log(s / d)
    return np.linalg.inv(_kron_reduce(p, n_phases))


@dataclass(frozen=True)
class LineCode:
    """A line code: series impedance [ohm/km] and shunt capacitance [nF/km] matrices of its phases, ampacity [A]."""

    name: str
    n_phases: int
    z_ohm_per_km: np.ndarray = field(repr=False)
    c_nf_per_km: np.ndarray = field(repr=False)
    ampacity_a: float

    @property
    def z1_ohm_per_km(self) -> complex:
        """Per-phase impedance used by the drop estimate: positive sequence (3 ph) or self (1 ph)."""
        z = self.z_ohm_per_km
        if self.n_phases == 1:
            return complex(z[0, 0])
        return complex(np.mean(np.diag(z)) - (z.sum() - np.trace(z)) / 6.0)


# Pole-top geometries [ft]: Kersting's ID-500 three-phase crossarm (phases at 28 ft, neutral at 24 ft)
# and a single-phase pole with the neutral 4 ft below the phase conductor.
_XY_3PH_FT = np.array([[0.0, 28.0], [2.5, 28.0], [7.0, 28.0], [4.0, 24.0]])
_XY_1PH_FT = np.array([[0.0, 29.0], [0.5, 25.0]])


def _make_linecode(name: str, phase: str, neutral: str, n_phases: int) -> LineCode:
    xy = _XY_3PH_FT if n_phases == 3 else _XY_1PH_FT
    conds = [CONDUCTORS[phase]] * n_phases + [CONDUCTORS[neutral]]
    z = phase_impedance_ohm_per_mile(
        xy, np.array([c.r_ohm_per_mile for c in conds]), np.array([c.gmr_ft for c in conds]), n_phases
    )
    c = phase_capacitance_uf_per_mile(xy, np.array([c.diameter_in for c in conds]), n_phases)
    return LineCode(
        name, n_phases, z / _KM_PER_MILE, c * 1000.0 / _KM_PER_MILE, CONDUCTORS[phase].ampacity_a
    )


LINECODES = {
    lc.name: lc
    for lc in (
        _make_linecode("ph3_336", "336_acsr", "4/0_acsr", 3),
        _make_linecode("ph3_1_0", "1/0_acsr", "1/0_acsr", 3),
        _make_linecode("ph1_2", "2_acsr", "2_acsr", 1),
        _make_linecode("ph1_4", "4_acsr", "4_acsr", 1),
    )
}
