"""Geodetic (WGS84 lat, lon, ellipsoidal height) <-> local East-North-Up metres around an origin."""

from __future__ import annotations

from functools import cached_property

import numpy as np
from pyproj import Transformer


class ENUFrame:
    """A local tangent-plane frame at ``(lat, lon, alt_m)`` on the WGS84 ellipsoid.

    Positions go through pyproj's ``cart`` + ``topocentric`` pipeline (exact, not a flat-earth
    approximation). Velocities given in the local ENU frame of each point (what ADS-B
    reports) are rotated into this frame's axes.
    """

    def __init__(self, lat: float, lon: float, alt_m: float = 0.0):
        if not (-90 <= lat <= 90 and -180 <= lon <= 180 and np.isfinite(alt_m)):
            raise ValueError(f"origin out of range: lat={lat}, lon={lon}, alt_m={alt_m}")
        self.lat, self.lon, self.alt_m = float(lat), float(lon), float(alt_m)

    @cached_property
    def _transformer(self) -> Transformer:
        pipeline = (
            "+proj=pipeline +step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={self.lat} +lon_0={self.lon} +h_0={self.alt_m}"
        )
        return Transformer.from_pipeline(pipeline)

    def to_enu(self, lat, lon, alt_m) -> np.ndarray:
        """(N, 3) east, north, up in metres."""
        e, n, u = self._transformer.transform(
            np.asarray(lon, float), np.asarray(lat, float), np.asarray(alt_m, float)
        )
        return np.stack([e, n, u], axis=-1)

    def to_geodetic(self, enu) -> np.ndarray:
        """(N, 3) lat, lon (degrees), alt_m from ENU metres."""
        enu = np.asarray(enu, float)
        lon, lat, alt = self._transformer.transform(
            enu[..., 0], enu[..., 1], enu[..., 2], direction="INVERSE"
        )
        return np.stack([lat, lon, alt], axis=-1)

    def rotate_velocity(self, lat, lon, v_local) -> np.ndarray:
        """Velocities in each point's own ENU axes -> this frame's ENU axes, (N, 3)."""
        to_ecef = _enu_to_ecef(np.radians(lat), np.radians(lon))  # (N, 3, 3)
        from_ecef = _enu_to_ecef(np.radians(self.lat), np.radians(self.lon)).T
        return np.einsum("ij,njk,nk->ni", from_ecef, to_ecef, np.asarray(v_local, float))


def _enu_to_ecef(lat, lon) -> np.ndarray:
    """Rotation whose columns are the east, north, up unit vectors in ECEF."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl)
    east = np.stack([-so, co, zero], -1)
    north = np.stack([-sl * co, -sl * so, cl], -1)
    up = np.stack([cl * co, cl * so, sl], -1)
    return np.stack([east, north, up], -1)
