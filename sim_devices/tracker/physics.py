"""The simulated tracker's physics, written on its own: a station, a distance meter and two encoder angles, the
refraction of the air, the MPE-shaped noise, the line of sight and emScon's units.

**Measuring.** A reflector at p (base frame) is at q = Rᵀ (p − t) in the tracker's frame (the station: p_base =
R p_tracker + t). The tracker measures the distance d = |q|, the horizontal angle Hz = atan2(q_y, q_x)
(counter-clockwise from x) and the zenith angle V = arccos(q_z / d) (0 up, 90° level), and reports
(d sin V cos Hz, d sin V sin Hz, d cos V): x, y, z in its own frame.

**Noise.** The maximum permissible error U(d) = ±(a + b·d) (a = 15 µm, b = 6 µm/m) is read as a k = 2 bound on the
radial error and on each of the two transverse errors, so each has σ(d) = U(d)/2: the distance meter draws
N(0, σ²); the vertical encoder N(0, (σ/d)²) and the horizontal one N(0, (σ/(d sin V))²), i.e. σ across the beam
both ways. The point's error is then isotropic: σ on x, y and z alike (what the tracker states as its standard
deviations).

**Refraction.** The distance meter counts wavelengths in air: it finds the optical path n_true·d and divides by the
refractive index n_set it computes from the environment the client set (or the index set directly), so it reports
d·n_true/n_set: a pressure 1 hPa too high makes every distance about 0.27 µm/m short. Both indices come from NIST's
simple shop-floor formula, a simplification of the (modified) Edlén equation for 633 nm, good to a few parts in 10⁷
in ordinary shop conditions (J. A. Stone, J. H. Zimmerman, "Index of Refraction of Air", NIST Engineering Metrology
Toolbox, Refractive Index of Air Calculator, Appendix B, emtoolbox.nist.gov/Wavelength/Documentation.asp):

    n = 1 + 7.86e-4 · p / (273 + t) − 1.5e-11 · RH · (t² + 160)     (p in kPa, t in °C, RH in %)

used alike for the interferometer and the absolute distance meter (the ADM's group index differs from the phase
index by a few per cent of n − 1, which this simulator leaves out).

**Set up again.** ``moved_station``: the operator moves the tracker near its place, its origin by a distance
along some direction and its frame by an angle about some axis through its origin.

**Line of sight.** A reflector is seen when its distance lies within the tracker's range and the straight beam from
the tracker's origin to it passes no obstacle sphere.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hilcal.protocols.emscon import AngleUnit, LengthUnit, PressureUnit, TemperatureUnit
from sim_devices.rotation import matrix_from_rotvec, matrix_from_rpy_deg, rpy_deg_from_matrix

MM_PER_LENGTH_UNIT = {
    LengthUnit.Meter: 1000.0,
    LengthUnit.Millimeter: 1.0,
    LengthUnit.Micron: 1e-3,
    LengthUnit.Foot: 304.8,
    LengthUnit.Yard: 914.4,
    LengthUnit.Inch: 25.4,
}
RAD_PER_ANGLE_UNIT = {AngleUnit.Radian: 1.0, AngleUnit.Degree: np.pi / 180.0, AngleUnit.Gon: np.pi / 200.0}
HPA_PER_PRESSURE_UNIT = {
    PressureUnit.Mbar: 1.0,
    PressureUnit.HPascal: 1.0,
    PressureUnit.KPascal: 10.0,
    PressureUnit.MmHg: 1.33322387415,
    PressureUnit.Psi: 68.9475729318,
    PressureUnit.InH2O: 2.49088908333,
    PressureUnit.InHg: 33.8638864,
}
MIN_TRANSVERSE_MM = 1.0
"""The horizontal encoder's noise is taken at least this far from the vertical axis (it is undefined on it)."""


def refractive_index(temperature_c: float, pressure_hpa: float, humidity_pct: float) -> float:
    """The NIST shop-floor index of refraction of air (see the module docstring)."""
    p_kpa = pressure_hpa / 10.0
    t = temperature_c
    return 1.0 + 7.86e-4 * p_kpa / (273.0 + t) - 1.5e-11 * humidity_pct * (t * t + 160.0)


def to_celsius(value: float, unit: int) -> float:
    return value if unit == TemperatureUnit.Celsius else (value - 32.0) * 5.0 / 9.0


def from_celsius(value_c: float, unit: int) -> float:
    return value_c if unit == TemperatureUnit.Celsius else value_c * 9.0 / 5.0 + 32.0


def station_transform(station_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a station [x, y, z mm, roll, pitch, yaw deg]: p_base = R p_tracker + t."""
    p = np.asarray(station_pose, dtype=float)
    R = matrix_from_rpy_deg(p[3:])
    return R, p[:3].copy()


def station_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[x, y, z mm, roll, pitch, yaw deg] of a station (R, t), the inverse of ``station_transform``."""
    return np.concatenate([np.asarray(t, dtype=float), rpy_deg_from_matrix(R)])


def moved_station(R: np.ndarray, t: np.ndarray, move_mm: float, move_deg: float, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The station (R, t) set up again near its place: its origin shifted by ``move_mm`` along a random direction and
    its frame turned by ``move_deg`` about a random axis through its origin (both drawn from ``rng``, base frame)."""
    direction, axis = rng.normal(size=3), rng.normal(size=3)
    turn = matrix_from_rotvec(np.radians(move_deg) * axis / np.linalg.norm(axis))
    return turn @ R, np.asarray(t, dtype=float) + move_mm * direction / np.linalg.norm(direction)


def to_tracker(points_base_mm: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Base-frame points (..., 3) in the tracker's frame."""
    return (np.asarray(points_base_mm, dtype=float) - t) @ R


def spherical(q_mm: np.ndarray) -> tuple[float, float, float]:
    """(distance mm, horizontal angle rad, zenith angle rad) of a point in the tracker's frame."""
    q = np.asarray(q_mm, dtype=float)
    d = float(np.linalg.norm(q))
    return d, float(np.arctan2(q[1], q[0])), float(np.arccos(np.clip(q[2] / d, -1.0, 1.0)))


def cartesian(distance_mm: float, hz_rad: float, v_rad: float) -> np.ndarray:
    """The point of a distance, horizontal angle and zenith angle."""
    s = np.sin(v_rad)
    return distance_mm * np.array([s * np.cos(hz_rad), s * np.sin(hz_rad), np.cos(v_rad)])


def mpe_mm(distance_mm: float, constant_um: float, per_m_um: float) -> float:
    """U(d) = constant + per_m · d, mm."""
    return (constant_um + per_m_um * distance_mm / 1000.0) / 1000.0


def measure(q_true_mm: np.ndarray, sigma_mm: float, scale: float, rng: np.random.Generator) -> np.ndarray:
    """The point the tracker reports for a reflector at ``q_true_mm`` (its frame): the distance times ``scale``
    (n_true / n_set) and the three readings with σ of ``sigma_mm`` along the beam and across it both ways."""
    d, hz, v = spherical(q_true_mm)
    noise = rng.normal(0.0, 1.0, 3) * sigma_mm
    d_meas = (d + noise[0]) * scale
    v_meas = v + noise[1] / d
    hz_meas = hz + noise[2] / max(d * np.sin(v), MIN_TRANSVERSE_MM)
    return cartesian(d_meas, hz_meas, v_meas)


def blocked(target_mm: np.ndarray, obstacles: Sequence[tuple[np.ndarray, float]]) -> bool:
    """Whether the beam from the origin to ``target_mm`` passes through an obstacle sphere (centre, radius), all in
    the tracker's frame."""
    q = np.asarray(target_mm, dtype=float)
    length2 = float(q @ q)
    for centre, radius in obstacles:
        s = float(np.clip((centre @ q) / length2, 0.0, 1.0)) if length2 > 0 else 0.0
        if float(np.linalg.norm(centre - s * q)) < radius:
            return True
    return False
