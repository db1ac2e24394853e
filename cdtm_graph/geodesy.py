"""WGS84 geodesy: the local ENU world of a geodetic origin, normal gravity, Earth rate, geoid.

A flight log with a top-level ``origin:`` (flight.yaml) has as its world frame the local
East-North-Up tangent plane at that point: x east, y north, z up along the WGS84 ellipsoid
normal, origin at the given latitude, longitude and ellipsoidal height. Everything inside
the estimator stays metric in that frame; geodetic coordinates are converted at the edges
(readers, DEM import, outputs) by :class:`LocalFrame`.

- Geodetic <-> ECEF conversions are PROJ's (pyproj, EPSG:4979 <-> EPSG:4978); ECEF <->
  world is one rotation and one translation (exact, numpy).
- Normal gravity is WGS84's (NIMA TR8350.2, 3rd ed., ch. 4): Somigliana's closed form on
  the ellipsoid, the second-order series in height above it, along the ellipsoid normal,
  plus the small northward component the normal field has above the ellipsoid (Groves,
  *Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems*, 2nd ed.,
  eq. 2.140). It is gravity as an IMU at rest on the rotating Earth senses it (gravitation
  plus centrifugal): a mechanization in the Earth-fixed world frame adds only the Coriolis
  term ``-2 omega x v``.
- The geoid is EGM96 from the 15' grid the package ships, ``cdtm_graph/data/geoid``
  (read by PROJ, offline).

Array conventions: latitudes and longitudes in degrees, heights and positions in metres,
``(N,)`` or ``(N, 3)`` arrays; rotations ``a_R_b`` map frame-b vectors into frame a.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdtm_graph.choices import VerticalDatum
from cdtm_graph.data import egm96_grid_file
from cdtm_graph.errors import CdtmError
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz

__all__ = [
    "WGS84_A_M",
    "WGS84_B_M",
    "WGS84_E2",
    "WGS84_F",
    "WGS84_GAMMA_EQUATOR_MPS2",
    "WGS84_GAMMA_POLE_MPS2",
    "WGS84_GM_M3PS2",
    "WGS84_OMEGA_RADPS",
    "GeodesyError",
    "GeodeticOrigin",
    "ImuEnvironment",
    "LocalFrame",
    "VerticalDatum",
    "enu_R_ecef",
    "ellipsoidal_height_m",
    "geoid_undulation_m",
    "normal_gravity_enu_mps2",
    "normal_gravity_mps2",
]

# WGS84 defining and derived constants (NIMA TR8350.2, tables 3.1 and 3.3).
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_GM_M3PS2 = 3.986004418e14
WGS84_OMEGA_RADPS = 7.292115e-5
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
#: Normal gravity on the ellipsoid at the equator and at the poles (TR8350.2 table 3.4).
WGS84_GAMMA_EQUATOR_MPS2 = 9.7803253359
WGS84_GAMMA_POLE_MPS2 = 9.8321849378
#: Somigliana's constant k = b gamma_p / (a gamma_e) - 1.
_SOMIGLIANA_K = WGS84_B_M * WGS84_GAMMA_POLE_MPS2 / (WGS84_A_M * WGS84_GAMMA_EQUATOR_MPS2) - 1.0
#: m = omega^2 a^2 b / GM, in the height series of normal gravity.
_M = WGS84_OMEGA_RADPS**2 * WGS84_A_M**2 * WGS84_B_M / WGS84_GM_M3PS2
#: North component of normal gravity above the ellipsoid: -8.08e-9 h sin(2 lat) m/s^2 per
#: metre of height (Groves eq. 2.140; checked against the normal potential's gradient).
_NORTH_GRAVITY_PER_M = -8.08e-9

#: Environment variable naming another copy of the EGM96 grid (the package ships one,
#: :func:`cdtm_graph.data.egm96_grid_file`; cdtm_graph/data/geoid/README.md).
EGM96_GRID_ENV = "CDTM_EGM96_GRID"


class GeodesyError(CdtmError):
    """A geodetic input is invalid (latitude out of range, missing geoid grid...)."""


def _as_float_array(name: str, value) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise GeodesyError(f"{name} holds a non-finite value; expected finite numbers")
    return arr


@dataclass(frozen=True)
class GeodeticOrigin:
    """The geodetic point the world frame is attached to (``origin:`` in flight.yaml).

    Attributes:
        latitude_deg: WGS84 geodetic latitude, degrees in [-90, 90].
        longitude_deg: WGS84 longitude, degrees in [-180, 360).
        height_m: WGS84 ellipsoidal height, metres.
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float

    def __post_init__(self) -> None:
        for name in ("latitude_deg", "longitude_deg", "height_m"):
            value = getattr(self, name)
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise GeodesyError(f"origin {name} = {value!r}; expected a number") from None
            if not math.isfinite(number):
                raise GeodesyError(f"origin {name} = {value!r}; expected a finite number")
            object.__setattr__(self, name, number)
        if not -90.0 <= self.latitude_deg <= 90.0:
            raise GeodesyError(f"origin latitude_deg = {self.latitude_deg!r}; "
                               "expected -90 <= latitude_deg <= 90")
        if not -180.0 <= self.longitude_deg < 360.0:
            raise GeodesyError(f"origin longitude_deg = {self.longitude_deg!r}; "
                               "expected -180 <= longitude_deg < 360")


# --------------------------------------------------------------------------- PROJ


@functools.cache
def _geodetic_to_ecef_transformer():
    from pyproj import Transformer

    # EPSG:4979 (WGS 84 geographic 3D) -> EPSG:4978 (WGS 84 geocentric): an exact conversion.
    return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def geodetic_to_ecef(latitude_deg, longitude_deg, height_m) -> np.ndarray:
    """ECEF positions of geodetic points (PROJ).

    Args:
        latitude_deg, longitude_deg, height_m: broadcastable arrays (deg, deg, m).

    Returns:
        (N, 3) ECEF metres (N = the broadcast size).
    """
    lat, lon, h = np.broadcast_arrays(_as_float_array("latitude_deg", latitude_deg),
                                      _as_float_array("longitude_deg", longitude_deg),
                                      _as_float_array("height_m", height_m))
    x, y, z = _geodetic_to_ecef_transformer().transform(lon.ravel(), lat.ravel(), h.ravel())
    return np.column_stack([x, y, z])


def ecef_to_geodetic(p_ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geodetic coordinates of ECEF positions (PROJ).

    Args:
        p_ecef: (N, 3) or (3,) ECEF metres.

    Returns:
        latitude_deg, longitude_deg (in [-180, 180]), height_m: (N,) each.
    """
    p = np.atleast_2d(_as_float_array("p_ecef", p_ecef))
    lon, lat, h = _geodetic_to_ecef_transformer().transform(
        p[:, 0], p[:, 1], p[:, 2], direction="INVERSE")
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def enu_R_ecef(latitude_deg, longitude_deg) -> np.ndarray:
    """Rotations from ECEF to the local ENU frame at geodetic points.

    Args:
        latitude_deg, longitude_deg: (N,) or scalars, degrees.

    Returns:
        (N, 3, 3): rows are the east, north and up unit vectors in ECEF.
    """
    lat, lon = np.broadcast_arrays(np.radians(np.asarray(latitude_deg, dtype=float)),
                                   np.radians(np.asarray(longitude_deg, dtype=float)))
    lat, lon = lat.ravel(), lon.ravel()
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    R = np.empty((lat.size, 3, 3))
    R[:, 0] = np.column_stack([-so, co, np.zeros_like(lat)])
    R[:, 1] = np.column_stack([-sl * co, -sl * so, cl])
    R[:, 2] = np.column_stack([cl * co, cl * so, sl])
    return R


# --------------------------------------------------------------------------- gravity


def normal_gravity_mps2(latitude_deg, height_m=0.0) -> np.ndarray:
    """Magnitude of WGS84 normal gravity (TR8350.2 eqs. 4-1 and 4-3).

    ``gamma(lat) = gamma_e (1 + k sin^2 lat) / sqrt(1 - e^2 sin^2 lat)`` (Somigliana) on
    the ellipsoid, times ``1 - 2/a (1 + f + m - 2 f sin^2 lat) h + 3 h^2 / a^2`` at
    ellipsoidal height h (second order in h/a). Measured against the gradient of the
    closed-form normal potential (tests/core/test_geodesy.py): within 1.1e-7 m/s^2 up to 1 km
    and 1.5e-6 m/s^2 (0.15 micro-g) up to 20 km.

    Args:
        latitude_deg: geodetic latitude, degrees (any shape).
        height_m: ellipsoidal height, metres (broadcast against latitude).

    Returns:
        Normal gravity, m/s^2, with the broadcast shape.
    """
    s2 = np.sin(np.radians(np.asarray(latitude_deg, dtype=float))) ** 2
    h = np.asarray(height_m, dtype=float)
    gamma0 = WGS84_GAMMA_EQUATOR_MPS2 * (1.0 + _SOMIGLIANA_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)
    series = (1.0 - 2.0 / WGS84_A_M * (1.0 + WGS84_F + _M - 2.0 * WGS84_F * s2) * h
              + 3.0 * h**2 / WGS84_A_M**2)
    return gamma0 * series


def normal_gravity_enu_mps2(latitude_deg, height_m=0.0) -> np.ndarray:
    """WGS84 normal gravity vector in the local ENU frame at the point.

    Down along the ellipsoid normal with :func:`normal_gravity_mps2`'s magnitude, plus
    the northward component ``-8.08e-9 h sin(2 lat)`` m/s^2 of the normal field above the
    ellipsoid (Groves eq. 2.140; 8e-6 m/s^2 at 1 km, 45 deg).

    Args:
        latitude_deg, height_m: broadcastable (N,) arrays or scalars.

    Returns:
        (N, 3) gravity (east, north, up), m/s^2: gravitation plus centrifugal, what an
        accelerometer at rest on the Earth reads with the opposite sign.
    """
    lat, h = np.broadcast_arrays(np.asarray(latitude_deg, dtype=float),
                                 np.asarray(height_m, dtype=float))
    lat, h = lat.ravel(), h.ravel()
    g = np.zeros((lat.size, 3))
    g[:, 1] = _NORTH_GRAVITY_PER_M * h * np.sin(2.0 * np.radians(lat))
    g[:, 2] = -normal_gravity_mps2(lat, h)
    return g


# --------------------------------------------------------------------------- geoid


@functools.cache
def _geoid_transformer(grid: str):
    from pyproj import Transformer
    from pyproj.exceptions import ProjError

    # vgridshift adds multiplier * N to z: from height above the geoid to above the ellipsoid.
    pipeline = ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
                f"+step +proj=vgridshift +grids={grid} +multiplier=1 "
                "+step +proj=unitconvert +xy_in=rad +xy_out=deg")
    try:
        return Transformer.from_pipeline(pipeline)
    except ProjError as exc:
        raise GeodesyError(f"{grid}: PROJ cannot use the EGM96 grid ({exc}); expected the "
                           "GeoTIFF cdtm_graph/data/geoid/egm96_15.tif (its README.md)") from None


def egm96_grid_path() -> Path:
    """The EGM96 grid file: ``$CDTM_EGM96_GRID`` if set, else the package's own copy.

    Raises:
        GeodesyError: the file does not exist.
    """
    override = os.environ.get(EGM96_GRID_ENV)
    path = Path(override) if override else egm96_grid_file()
    if not path.is_file():
        raise GeodesyError(f"{path}: EGM96 geoid grid not found; expected the package's "
                           f"cdtm_graph/data/geoid/egm96_15.tif, or {EGM96_GRID_ENV} naming a "
                           "copy (scripts/make_geoid_grid.py builds it)")
    return path


def geoid_undulation_m(latitude_deg, longitude_deg) -> np.ndarray:
    """EGM96 geoid height N above the WGS84 ellipsoid (m), bilinear on the 15' grid.

    Ellipsoidal height = height above the geoid (SRTM, Copernicus GLO-30, "MSL") + N.
    Offline: PROJ reads the grid file of :func:`egm96_grid_path`.

    Args:
        latitude_deg, longitude_deg: broadcastable arrays, degrees.

    Returns:
        N in metres, (N,) for the broadcast size.

    Raises:
        GeodesyError: the grid is missing or unreadable, or a point is off it.
    """
    lat, lon = np.broadcast_arrays(_as_float_array("latitude_deg", latitude_deg),
                                   _as_float_array("longitude_deg", longitude_deg))
    lat, lon = lat.ravel(), lon.ravel()
    transformer = _geoid_transformer(str(egm96_grid_path().resolve()))
    _, _, n = transformer.transform(lon, lat, np.zeros_like(lat))
    n = np.asarray(n, dtype=float)
    if not np.all(np.isfinite(n)):
        bad = int(np.flatnonzero(~np.isfinite(n))[0])
        raise GeodesyError(f"no EGM96 geoid height at latitude {lat[bad]!r}, longitude "
                           f"{lon[bad]!r}; expected -90 <= latitude <= 90")
    return n


def ellipsoidal_height_m(datum: VerticalDatum, latitude_deg, longitude_deg,
                        height_m) -> np.ndarray:
    """Ellipsoidal heights (N,) of heights in ``datum`` at geodetic points (N,)."""
    height = np.asarray(height_m, dtype=float).ravel()
    if datum is VerticalDatum.ELLIPSOID:
        return height.copy()
    return height + geoid_undulation_m(latitude_deg, longitude_deg)


# --------------------------------------------------------------------------- local frame


@dataclass(frozen=True)
class ImuEnvironment:
    """What an Earth-aware IMU preintegration needs for one interval, in the world frame.

    Attributes:
        gravity_mps2: (3,) normal gravity (gravitation + centrifugal) at the interval's
            position, world frame.
        earth_rate_radps: (3,) the Earth's rotation rate in the world frame (GTSAM's
            ``omegaCoriolis``; the same for every interval).
    """

    gravity_mps2: np.ndarray
    earth_rate_radps: np.ndarray

    def gtsam_n_gravity(self, start_position_m: np.ndarray) -> np.ndarray:
        """``n_gravity`` to give GTSAM 4.3's ``PreintegrationParams`` for this interval.

        With ``omegaCoriolis`` set, GTSAM 4.3's predict adds the centrifugal term
        ``-Omega x (Omega x p_i)`` of the interval's start position ``p_i`` (in the world,
        from the world origin) to the gravity it is given (its second-order Coriolis term;
        4.3's Python API cannot switch it off; measured in tests/core/test_geodesy.py). Normal
        gravity already holds the centrifugal acceleration, so GTSAM must get
        ``gravity + Omega x (Omega x p_i)``: the two cancel and the result is the normal
        gravity (1.6e-4 m/s^2 at 30 km from the origin otherwise, 2.6 m after 240 s).

        Args:
            start_position_m: (3,) the interval's start position in the world (the
                position of the state GTSAM predicts from).

        Returns:
            (3,) m/s^2.
        """
        omega = self.earth_rate_radps
        p = np.asarray(start_position_m, dtype=float).reshape(3)
        return self.gravity_mps2 + np.cross(omega, np.cross(omega, p))


class LocalFrame:
    """The world frame of a geodetic log: ENU at a :class:`GeodeticOrigin`.

    ``p_world = world_R_ecef (p_ecef - origin_ecef_m)``; the world frame is fixed to the
    rotating Earth.

    Attributes:
        origin: the geodetic origin.
        origin_ecef_m: (3,) the origin in ECEF.
        world_R_ecef: (3, 3) rotation from ECEF to the world (ENU at the origin).
    """

    def __init__(self, origin: GeodeticOrigin):
        from pyproj import Transformer

        self.origin = origin
        self.origin_ecef_m = geodetic_to_ecef(origin.latitude_deg, origin.longitude_deg,
                                              origin.height_m)[0]
        self.world_R_ecef = enu_R_ecef(origin.latitude_deg, origin.longitude_deg)[0]
        # World -> geodetic in one PROJ pipeline (its topocentric conversion is this frame:
        # tests/core/test_geodesy.py compares it with world_R_ecef and origin_ecef_m).
        self._world_to_geodetic = Transformer.from_pipeline(
            "+proj=pipeline "
            f"+step +inv +proj=topocentric +ellps=WGS84 +lat_0={origin.latitude_deg!r} "
            f"+lon_0={origin.longitude_deg!r} +h_0={origin.height_m!r} "
            "+step +inv +proj=cart +ellps=WGS84 "
            "+step +proj=unitconvert +xy_in=rad +xy_out=deg")

    def __repr__(self) -> str:
        o = self.origin
        return (f"LocalFrame(latitude_deg={o.latitude_deg}, longitude_deg={o.longitude_deg}, "
                f"height_m={o.height_m})")

    # -- positions ---------------------------------------------------------------------

    def ecef_to_world(self, p_ecef: np.ndarray) -> np.ndarray:
        """(N, 3) ECEF -> (N, 3) world metres."""
        return _rotate(self.world_R_ecef,
                       np.atleast_2d(np.asarray(p_ecef, dtype=float)) - self.origin_ecef_m)

    def world_to_ecef(self, p_world: np.ndarray) -> np.ndarray:
        """(N, 3) world -> (N, 3) ECEF metres."""
        return _rotate(self.world_R_ecef.T, np.atleast_2d(np.asarray(p_world, dtype=float))) \
            + self.origin_ecef_m

    def geodetic_to_world(self, latitude_deg, longitude_deg, height_m) -> np.ndarray:
        """World positions of geodetic points (PROJ).

        Args:
            latitude_deg, longitude_deg, height_m: broadcastable arrays (deg, deg,
                ellipsoidal m).

        Returns:
            (N, 3) world metres.
        """
        lat, lon, h = np.broadcast_arrays(_as_float_array("latitude_deg", latitude_deg),
                                          _as_float_array("longitude_deg", longitude_deg),
                                          _as_float_array("height_m", height_m))
        x, y, z = self._world_to_geodetic.transform(lon.ravel(), lat.ravel(), h.ravel(),
                                                    direction="INVERSE")
        return np.column_stack([x, y, z])

    def world_to_geodetic(self, p_world: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic coordinates of world positions (PROJ).

        Args:
            p_world: (N, 3) or (3,) world metres.

        Returns:
            latitude_deg, longitude_deg (in [-180, 180]), height_m (ellipsoidal): (N,).
        """
        p = np.atleast_2d(_as_float_array("p_world", p_world))
        lon, lat, h = self._world_to_geodetic.transform(p[:, 0], p[:, 1], p[:, 2])
        return np.asarray(lat), np.asarray(lon), np.asarray(h)

    # -- directions --------------------------------------------------------------------

    def world_R_enu(self, latitude_deg, longitude_deg) -> np.ndarray:
        """Rotations from the local ENU frame at geodetic points to the world frame.

        The identity at the origin; at 50 km from it the two verticals differ by 0.45 deg.

        Args:
            latitude_deg, longitude_deg: (N,) or scalars, degrees.

        Returns:
            (N, 3, 3).
        """
        return self.world_R_ecef @ np.swapaxes(enu_R_ecef(latitude_deg, longitude_deg), 1, 2)

    def up_z(self, latitude_deg, longitude_deg) -> np.ndarray:
        """World z component (N,) of the local vertical at geodetic points: the cosine of
        the angle between it and the world's up (0.9999556 at 60 km from the origin)."""
        la = np.radians(np.asarray(latitude_deg, dtype=float))
        lo = np.radians(np.asarray(longitude_deg, dtype=float))
        r = self.world_R_ecef[2]
        return r[0] * np.cos(la) * np.cos(lo) + r[1] * np.cos(la) * np.sin(lo) + r[2] * np.sin(la)

    def world_R_enu_at(self, p_world: np.ndarray) -> np.ndarray:
        """:meth:`world_R_enu` at world positions (N, 3) -> (N, 3, 3)."""
        lat, lon, _ = self.world_to_geodetic(p_world)
        return self.world_R_enu(lat, lon)

    # -- physics -----------------------------------------------------------------------

    @property
    def earth_rate_world_radps(self) -> np.ndarray:
        """(3,) the Earth's rotation rate in the world frame: ``Omega (0, cos lat0, sin lat0)``."""
        return self.world_R_ecef @ np.array([0.0, 0.0, WGS84_OMEGA_RADPS])

    def gravity_world_mps2(self, p_world: np.ndarray) -> np.ndarray:
        """WGS84 normal gravity at world positions, in the world frame.

        Args:
            p_world: (N, 3) or (3,) world metres.

        Returns:
            (N, 3) m/s^2: :func:`normal_gravity_enu_mps2` at each point's latitude and
            height, turned from the point's ENU into the world (its "down" leans away
            from the world's -z by the angle between the two verticals).
        """
        lat, lon, h = self.world_to_geodetic(p_world)
        return np.einsum("nij,nj->ni", self.world_R_enu(lat, lon),
                         normal_gravity_enu_mps2(lat, h))

    def imu_environment(self, p_world: np.ndarray) -> ImuEnvironment:
        """Gravity and Earth rate in the world frame for one preintegration interval.

        For GTSAM's ``PreintegrationParams`` per interval: evaluate this at the interval's
        midpoint (the start position plus half the predicted displacement: gravity turns
        along the track, 6e-5 m/s^2 per km), set ``omegaCoriolis = earth_rate_radps`` and
        ``n_gravity = gtsam_n_gravity(start position)``.
        ``scripts/flat_earth_error.py`` integrates a perfect IMU of a 60 km flight this way
        (docs/geodesy.md has the figures).

        Args:
            p_world: (3,) world position, metres.

        Returns:
            The :class:`ImuEnvironment`.
        """
        p = np.asarray(p_world, dtype=float).reshape(3)
        return ImuEnvironment(self.gravity_world_mps2(p)[0], self.earth_rate_world_radps)

    # -- states ------------------------------------------------------------------------

    def states_from_geodetic(self, latitude_deg, longitude_deg, height_m,
                             enu_quat_wxyz: np.ndarray, enu_velocity_mps: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World states from geodetic ones whose attitude and velocity are in the local ENU.

        Args:
            latitude_deg, longitude_deg, height_m: (N,) geodetic positions.
            enu_quat_wxyz: (N, 4) quaternions rotating body vectors into the local ENU at
                each position.
            enu_velocity_mps: (N, 3) velocity (east, north, up) in the local ENU.

        Returns:
            position_m (N, 3), quaternion_wxyz (N, 4) body -> world, velocity_mps (N, 3)
            in the world frame.
        """
        lat = np.atleast_1d(np.asarray(latitude_deg, dtype=float))
        lon = np.atleast_1d(np.asarray(longitude_deg, dtype=float))
        position = self.geodetic_to_world(lat, lon, height_m)
        world_R_enu = self.world_R_enu(lat, lon)
        world_R_body = world_R_enu @ quat_wxyz_to_rotation(np.atleast_2d(enu_quat_wxyz))
        velocity = np.einsum("nij,nj->ni", world_R_enu, np.atleast_2d(enu_velocity_mps))
        return position, rotation_to_quat_wxyz(world_R_body), velocity

    def states_to_geodetic(self, position_m: np.ndarray, world_R_body: np.ndarray,
                           velocity_mps: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The inverse of :meth:`states_from_geodetic`.

        Args:
            position_m: (N, 3) world positions. world_R_body: (N, 3, 3).
            velocity_mps: (N, 3) world velocities.

        Returns:
            latitude_deg, longitude_deg, height_m (N,), enu_quat_wxyz (N, 4) body -> local
            ENU, enu_velocity_mps (N, 3).
        """
        lat, lon, h = self.world_to_geodetic(position_m)
        enu_R_world = np.swapaxes(self.world_R_enu(lat, lon), 1, 2)
        quat = rotation_to_quat_wxyz(enu_R_world @ np.asarray(world_R_body, dtype=float))
        velocity = np.einsum("nij,nj->ni", enu_R_world, np.atleast_2d(velocity_mps))
        return lat, lon, h, quat, velocity

    def covariance_to_enu(self, position_m: np.ndarray, cov_world: np.ndarray) -> np.ndarray:
        """(N, 3, 3) world-frame position covariances -> the local ENU at each position."""
        enu_R_world = np.swapaxes(self.world_R_enu_at(position_m), 1, 2)
        return enu_R_world @ cov_world @ np.swapaxes(enu_R_world, 1, 2)


def _rotate(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 3) rows ``R @ p_i``, column by column (numpy's (N,3)@(3,3) matmul is 4x slower)."""
    return np.column_stack([p[:, 0] * R[i, 0] + p[:, 1] * R[i, 1] + p[:, 2] * R[i, 2]
                            for i in range(3)])


@functools.lru_cache(maxsize=16)
def local_frame(origin: GeodeticOrigin) -> LocalFrame:
    """The :class:`LocalFrame` of an origin, built once per origin."""
    return LocalFrame(origin)
