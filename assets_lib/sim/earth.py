"""Earth rate and local gravity in a local level frame (ENU or NED)."""

from __future__ import annotations

import numpy as np

#: WGS-84 earth rotation rate [rad/s] (NIMA TR8350.2 table 3.1).
EARTH_RATE_RADPS = 7.2921150e-5
_A = 6378137.0
_F = 1.0 / 298.257223563
_GE = 9.7803253359
_K = 0.00193185265241
_E2 = 0.00669437999013
_M = 0.00344978650684


def normal_gravity_mps2(latitude_deg: float, height_m: float = 0.0) -> float:
    """WGS-84 normal gravity: Somigliana's closed formula (NIMA TR8350.2 eq. 4-1) with the eq. 4-3 height series."""
    s2 = np.sin(np.radians(latitude_deg)) ** 2
    g0 = _GE * (1 + _K * s2) / np.sqrt(1 - _E2 * s2)
    return float(g0 * (1 - 2 / _A * (1 + _F + _M - 2 * _F * s2) * height_m + 3 * height_m**2 / _A**2))


def site_gravity_mps2(site) -> float:
    """Local gravity of a ``raw_schemas.Site``: the given value, or WGS-84 normal gravity at its latitude and height."""
    if site.gravity_model == "given" or site.gravity_mps2 is not None:
        return float(site.gravity_mps2)
    return normal_gravity_mps2(site.latitude_deg, site.height_m)


def earth_rate_level(latitude_deg: float, frame: str = "ENU") -> np.ndarray:
    """Earth rate in the level frame [rad/s]: ENU Omega [0, cos lat, sin lat]; NED Omega [cos lat, 0, -sin lat]."""
    lat = np.radians(latitude_deg)
    if frame == "ENU":
        return EARTH_RATE_RADPS * np.array([0.0, np.cos(lat), np.sin(lat)])
    if frame == "NED":
        return EARTH_RATE_RADPS * np.array([np.cos(lat), 0.0, -np.sin(lat)])
    raise ValueError(f"unknown level frame {frame!r}")


def specific_force_level(gravity_mps2: float, frame: str = "ENU") -> np.ndarray:
    """Specific force of an IMU at rest in the level frame [m/s^2]: it points up (ENU [0,0,g], NED [0,0,-g])."""
    if frame == "ENU":
        return np.array([0.0, 0.0, gravity_mps2])
    if frame == "NED":
        return np.array([0.0, 0.0, -gravity_mps2])
    raise ValueError(f"unknown level frame {frame!r}")
