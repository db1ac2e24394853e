"""flight.yaml: walked node by node, so every message names the offending line.

Every number must also lie within physical sense (:data:`RANGES`): beyond it a value is a
typo or a unit mix-up (degrees for radians, feet, a missing exponent), and IEEE overflow
would otherwise surface deep in the solver as a traceback or a silent NaN. The ranges are
wide, orders of magnitude around real sensors and flights; the error names the key, the
line and the accepted range.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import yaml

from cdtm_graph.camera import DISTORTION_LENGTHS, DistortionModel, PinholeCamera
from cdtm_graph.errors import CdtmError, why_not_a_file
from cdtm_graph.flightlog.model import (
    DTM_SUFFIXES,
    FORMAT,
    GEODETIC_DTM_SUFFIXES,
    QUATERNION_EXACT_TOL,
    QUATERNION_UNIT_TOL,
    CalibrationSigmas,
    CameraConfig,
    DtmConfig,
    FlightConfig,
    ImuConfig,
    InitialState,
    normalized_path,
)
from cdtm_graph.flightlog.problems import _fail, _show
from cdtm_graph.flightlog.tables import _parse_float
from cdtm_graph.geodesy import GeodeticOrigin, VerticalDatum, local_frame, normal_gravity_mps2
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation


@dataclass(frozen=True)
class Range:
    """Accepted values of one flight.yaml number (each component, for a vector)."""

    lo: float
    hi: float
    unit: str = ""

    def __str__(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"a number in [{self.lo:g}, {self.hi:g}]{unit}"


#: What each flight.yaml number may be. Sigmas and noise densities span orders of
#: magnitude around real sensors (a ring-laser gyro's 1.5e-7 to a cheap MEMS's 1e-3
#: rad/s/sqrt(Hz)); positions allow UTM-sized coordinates; gravity any planet a plane
#: or drone flies on (Moon 1.62 to Jupiter 24.8 m/s^2).
RANGES: dict[str, Range] = {
    "gravity_mps2": Range(1.0, 30.0, "m/s^2"),
    "dtm.sigma_h_m": Range(1e-4, 1e3, "m"),
    # a map registered within kilometres; 0: exactly (a simulation's own map)
    "dtm.horizontal_offset_sigma_m": Range(0.0, 1e4, "m"),
    "dtm.vertical_offset_sigma_m": Range(0.0, 1e3, "m"),
    "dtm.origin_enu_m": Range(-1e8, 1e8, "m"),
    # DEM import (geodetic logs): the margin around the prior track, up to 1000 km, and
    # the world grid's spacing, 1 cm (lidar) to 10 km; the grid itself is capped at
    # cdtm_graph.dem.MAX_GRID_NODES nodes.
    "dtm.margin_m": Range(1.0, 1e6, "m"),
    "dtm.spacing_m": Range(0.01, 1e4, "m"),
    "camera.pixel_sigma_px": Range(1e-3, 100.0, "px"),
    "camera.distortion_coeffs": Range(-1e3, 1e3),
    "camera.body_T_cam.translation_m": Range(-100.0, 100.0, "m"),
    # Camera-IMU clock offsets are milliseconds to a few hundred (USB cameras); seconds
    # mean clocks on different bases, to be fixed in the stamps, not here.
    "camera.time_offset_s": Range(-10.0, 10.0, "s"),
    # Online calibration priors (camera.calibration): a clock known to within a second at
    # worst, a mount to within 20 degrees, a focal length to within half its value.
    "camera.calibration.time_offset_sigma_s": Range(1e-6, 1.0, "s"),
    "camera.calibration.mount_sigma_deg": Range(1e-4, 20.0, "deg"),
    "camera.calibration.focal_scale_sigma": Range(1e-6, 0.5),
    # a principal point known to within 30 px at worst (a calibration, not a guess: its
    # first-order term holds to there, iSAM2's ANEES 2.5 at 30 px and 4.3 at 50 px for a
    # typical error, docs/verdict.md); 0: exactly (a simulation's own camera)
    "camera.principal_point_sigma_px": Range(0.0, 30.0, "px"),
    "imu.rate_hz": Range(1.0, 1e5, "Hz"),
    "imu.gyroscope_noise_density": Range(1e-9, 1e-1, "rad/s/sqrt(Hz)"),
    "imu.accelerometer_noise_density": Range(1e-7, 1.0, "m/s^2/sqrt(Hz)"),
    "imu.gyroscope_random_walk": Range(1e-12, 1e-1, "rad/s^2/sqrt(Hz)"),
    "imu.accelerometer_random_walk": Range(1e-10, 10.0, "m/s^3/sqrt(Hz)"),
    "initial_state.position_m": Range(-1e8, 1e8, "m"),
    "initial_state.velocity_mps": Range(-1e4, 1e4, "m/s"),
    "initial_state.gyro_bias": Range(-1.0, 1.0, "rad/s"),
    "initial_state.accel_bias": Range(-10.0, 10.0, "m/s^2"),
    "initial_state.sigma_position_m": Range(1e-6, 1e7, "m"),
    "initial_state.sigma_attitude_deg": Range(1e-6, 180.0, "deg"),
    "initial_state.sigma_velocity_mps": Range(1e-6, 1e4, "m/s"),
    "initial_state.sigma_gyro_bias": Range(1e-9, 1.0, "rad/s"),
    "initial_state.sigma_accel_bias": Range(1e-7, 10.0, "m/s^2"),
}
#: Image sides (px).
RESOLUTION_RANGE_PX = (2, 100_000)
#: Focal lengths fx, fy as multiples of the longer image side: a horizontal field of view
#: from about 157 degrees down to 0.06 degrees.
FOCAL_RANGE_SIDES = (0.1, 1000.0)
#: The principal point cx (cy) may lie this many image widths (heights) beyond the image.
PRINCIPAL_POINT_MARGIN_SIDES = 0.5


class _Yaml:
    """flight.yaml walked node by node, so every message can name the offending line."""

    def __init__(self, shown: str, loader: yaml.SafeLoader):
        self.shown = shown
        self.loader = loader

    @staticmethod
    def line(node: yaml.Node) -> int:
        return node.start_mark.line + 1

    def fail(self, node_or_line: yaml.Node | int, what: str, expected: str) -> NoReturn:
        line = node_or_line if isinstance(node_or_line, int) else self.line(node_or_line)
        _fail(self.shown, line, what, expected)

    def pairs(self, node: yaml.Node, name: str,
              line: int) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """Key -> (key node, value node) of a mapping; duplicate keys are an error."""
        if not isinstance(node, yaml.MappingNode):
            label = name or "the document"
            self.fail(line, f"{label} is not a mapping", f"a mapping of {label}'s keys")
        out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for key_node, value_node in node.value:
            key = self.value(key_node) if isinstance(key_node, yaml.ScalarNode) else None
            if not isinstance(key, str):
                self.fail(key_node, f"key {key!r} in {name} is not a name", "string keys")
            if key in out:
                self.fail(key_node, f"duplicate key '{_dotted(name, key)}'",
                          f"each key once (first on line {self.line(out[key][0])})")
            out[key] = (key_node, value_node)
        return out

    def keys(self, pairs: dict[str, tuple[yaml.Node, yaml.Node]], name: str, line: int,
             required: Sequence[str], optional: Sequence[str] = ()) -> dict[str, yaml.Node]:
        """Value nodes by key, after rejecting unknown keys and reporting missing ones."""
        allowed = tuple(required) + tuple(optional)
        for key, (key_node, _) in pairs.items():
            if key not in allowed:
                self.fail(key_node, f"unknown key '{_dotted(name, key)}'",
                          f"one of {', '.join(allowed)}"
                          + ("; free-form keys belong under extra:" if not name else ""))
        for key in required:
            if key not in pairs:
                self.fail(line, f"missing key '{_dotted(name, key)}'",
                          f"every required key of {name or 'the top level'}: "
                          f"{', '.join(required)}")
        return {key: value for key, (_, value) in pairs.items()}

    def value(self, node: yaml.Node) -> Any:
        try:
            return self.loader.construct_object(node, deep=True)
        except ValueError as exc:
            # Python refuses integers of more than 4300 digits (int_max_str_digits).
            token = node.value if isinstance(node, yaml.ScalarNode) else ""
            self.fail(node, f"value {_show(str(token))} cannot be read ({exc})".replace(
                "; use sys.set_int_max_str_digits() to increase the limit", ""),
                "a number of sensible size")

    def scalar(self, node: yaml.Node, name: str, expected: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            kind = "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"
            self.fail(node, f"{name} is {kind}", expected)
        return self.value(node)

    def number(self, node: yaml.Node, name: str, *, positive: bool = False,
               within: Range | None = None) -> float:
        expected = str(within) if within is not None else "a finite number"
        value = self.scalar(node, name, expected)
        number: float | None = None
        if isinstance(value, int | float) and not isinstance(value, bool):
            try:
                number = float(value)
            except OverflowError:  # an integer beyond float's range: as 1e400, infinite
                number = math.inf
        elif isinstance(value, str):
            # PyYAML (YAML 1.1) reads 1e-4 as a string; it is a number to anyone else.
            number = _parse_float(value)
        if number is None or not math.isfinite(number):
            self.fail(node, f"{name} is {_show(str(value))}", expected)
        if positive and not number > 0.0:
            self.fail(node, f"{name} is {number!r}", "a positive number")
        if within is not None and not within.lo <= number <= within.hi:
            self.fail(node, f"{name} is {number!r}", expected)
        return number

    def bounded(self, node: yaml.Node, key: str) -> float:
        """A number within ``RANGES[key]``."""
        return self.number(node, key, within=RANGES[key])

    def integer(self, node: yaml.Node, name: str) -> int:
        value = self.scalar(node, name, "a positive integer")
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            self.fail(node, f"{name} is {_show(str(value))}", "a positive integer")
        return value

    def text(self, node: yaml.Node, name: str) -> str:
        value = self.scalar(node, name, "a non-empty string")
        if not isinstance(value, str) or not value.strip():
            self.fail(node, f"{name} is {_show(str(value))}", "a non-empty string")
        return value

    def vector(self, node: yaml.Node, name: str, lengths: Sequence[int],
               bounded: bool = False) -> np.ndarray:
        """A list of numbers; with ``bounded``, each within ``RANGES[name]``."""
        want = " or ".join(str(n) for n in lengths)
        within = RANGES[name] if bounded else None
        expected = f"a list of {want} finite numbers" + (f", each {within}" if within else "")
        if not isinstance(node, yaml.SequenceNode):
            self.fail(node, f"{name} is {_show(str(self.scalar(node, name, expected)))}",
                      expected)
        if len(node.value) not in lengths:
            self.fail(node, f"{name} has {len(node.value)} values", expected)
        return np.array([self.number(item, f"{name}[{i}]", within=within)
                         for i, item in enumerate(node.value)])

    def quaternion(self, node: yaml.Node, name: str) -> np.ndarray:
        quat = self.vector(node, name, (4,))
        norm = float(np.linalg.norm(quat))
        if not abs(norm - 1.0) <= QUATERNION_UNIT_TOL:
            self.fail(node, f"{name} has norm {norm:.6g}",
                      f"a unit quaternion w,x,y,z (|norm - 1| <= {QUATERNION_UNIT_TOL:g})")
        return quat / norm if abs(norm - 1.0) > QUATERNION_EXACT_TOL else quat


def _dotted(parent: str, key: str) -> str:
    return f"{parent}.{key}" if parent else key


def _parse_flight_yaml(path: Path, shown: str, root: Path) -> FlightConfig:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        _fail(shown, 1 + path.read_bytes()[: exc.start].count(b"\n"), "not UTF-8 text",
              "a UTF-8 YAML file")
    loader = yaml.SafeLoader(text)
    try:
        return _parse_flight_document(loader, shown, root)
    except yaml.YAMLError as exc:
        # Syntax errors, and constructor errors such as an unknown !tag.
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        _fail(shown, mark.line + 1 if mark else 1, f"YAML error: {problem}", "valid YAML")
    finally:
        loader.dispose()


def _parse_flight_document(loader: yaml.SafeLoader, shown: str, root: Path) -> FlightConfig:
    document = loader.get_single_node()
    y = _Yaml(shown, loader)
    if document is None:
        _fail(shown, 1, "empty file", f"a mapping starting with format: {FORMAT}")
    top_pairs = y.pairs(document, "", 1)
    if "format" not in top_pairs:
        _fail(shown, 1, "missing key 'format'", f"format: {FORMAT}")
    format_node = top_pairs["format"][1]
    if y.value(format_node) != FORMAT:
        y.fail(format_node, f"format is {_show(str(y.value(format_node)))}", f"{FORMAT!r}")
    top = y.keys(top_pairs, "", 1, ("format", "dtm", "camera", "imu", "initial_state"),
                 ("gravity_mps2", "origin", "extra"))
    line_of = {key: y.line(key_node) for key, (key_node, _) in top_pairs.items()}

    origin = _parse_origin(y, top["origin"], line_of["origin"]) if "origin" in top else None
    if "gravity_mps2" in top:
        gravity = y.bounded(top["gravity_mps2"], "gravity_mps2")
    elif origin is not None:
        gravity = float(normal_gravity_mps2(origin.latitude_deg, origin.height_m))
    else:
        _fail(shown, 1, "missing key 'gravity_mps2'",
              "gravity_mps2 (m/s^2), or a top-level origin: (gravity from WGS84)")
    dtm = _parse_dtm(y, top["dtm"], line_of["dtm"], root, origin)
    camera = _parse_camera(y, top["camera"], line_of["camera"])
    imu = _parse_imu(y, top["imu"], line_of["imu"])
    initial = _parse_initial_state(y, top["initial_state"], line_of["initial_state"], origin)
    extra: dict = {}
    if "extra" in top:
        value = y.value(top["extra"])
        if value is not None and not isinstance(value, dict):
            y.fail(top["extra"], "extra is not a mapping", "extra: a mapping (or nothing)")
        extra = value or {}
    return FlightConfig(gravity, dtm, camera, imu, initial, extra, origin)


_ORIGIN_KEYS = ("latitude_deg", "longitude_deg", "height_m")


def _parse_origin(y: _Yaml, node: yaml.Node, line: int) -> GeodeticOrigin:
    m = y.keys(y.pairs(node, "origin", line), "origin", line, _ORIGIN_KEYS)
    values = {key: y.number(m[key], f"origin.{key}") for key in _ORIGIN_KEYS}
    if not -90.0 <= values["latitude_deg"] <= 90.0:
        y.fail(m["latitude_deg"], f"origin.latitude_deg is {values['latitude_deg']!r}",
               "a WGS84 latitude in degrees, -90 to 90")
    if not -180.0 <= values["longitude_deg"] < 360.0:
        y.fail(m["longitude_deg"], f"origin.longitude_deg is {values['longitude_deg']!r}",
               "a WGS84 longitude in degrees, -180 to 360")
    return GeodeticOrigin(**values)


def _dtm_file(y: _Yaml, node: yaml.Node, name: str, root: Path,
              suffixes: Sequence[str]) -> Path:
    text = y.text(node, name)
    given = Path(text)
    resolved = normalized_path(given if given.is_absolute() else root / given)
    if resolved.suffix.lower() not in suffixes:
        y.fail(node, f"{name} {_show(text)} has suffix {_show(resolved.suffix)}",
               f"a {', '.join(suffixes[:-1])} or {suffixes[-1]} file")
    if not resolved.is_file():
        y.fail(node, f"{name} {_show(text)} {why_not_a_file(resolved)} ({resolved})",
               "an existing DTM file, relative to the log directory or absolute")
    return resolved


def _parse_dtm(y: _Yaml, node: yaml.Node, line: int, root: Path,
               origin: GeodeticOrigin | None) -> DtmConfig:
    geodetic_keys = ("vertical_datum", "crs", "margin_m", "spacing_m")
    m = y.keys(y.pairs(node, "dtm", line), "dtm", line, ("path",),
               ("sigma_h_m", *DtmConfig.OFFSET_SIGMA_KEYS, "origin_enu_m", *geodetic_keys))
    suffixes = DTM_SUFFIXES if origin is None else GEODETIC_DTM_SUFFIXES
    path_node = m["path"]
    if isinstance(path_node, yaml.SequenceNode):
        if origin is None:
            y.fail(path_node, "dtm.path is a list of tiles without a geodetic origin",
                   "one DTM file, or a top-level origin: to mosaic georeferenced tiles")
        if not path_node.value:
            y.fail(path_node, "dtm.path is an empty list", "one or more DEM files")
        paths = [_dtm_file(y, item, f"dtm.path[{i}]", root, suffixes)
                 for i, item in enumerate(path_node.value)]
    else:
        paths = [_dtm_file(y, path_node, "dtm.path", root, suffixes)]
    sigma_h = None
    if "sigma_h_m" in m and y.value(m["sigma_h_m"]) is not None:
        sigma_h = y.bounded(m["sigma_h_m"], "dtm.sigma_h_m")
    offset_sigmas = {key: y.bounded(m[key], f"dtm.{key}")
                     for key in DtmConfig.OFFSET_SIGMA_KEYS
                     if key in m and y.value(m[key]) is not None}
    if origin is None:
        for key in geodetic_keys:
            if key in m:
                y.fail(m[key], f"dtm.{key} without a geodetic origin",
                       "a top-level origin: (latitude_deg, longitude_deg, height_m) "
                       f"for dtm.{key}")
        offset = (0.0, 0.0, 0.0)
        if "origin_enu_m" in m:
            offset = tuple(y.vector(m["origin_enu_m"], "dtm.origin_enu_m", (3,), True).tolist())
        return DtmConfig(paths[0], sigma_h, offset, **offset_sigmas)  # type: ignore[arg-type]
    if "origin_enu_m" in m:
        y.fail(m["origin_enu_m"], "dtm.origin_enu_m with a geodetic origin",
               "no origin_enu_m: georeferenced DEMs are placed by their CRS")
    if "vertical_datum" not in m:
        y.fail(line, "missing key 'dtm.vertical_datum'",
               "dtm.vertical_datum: ellipsoid or egm96 with a geodetic origin (SRTM and "
               "Copernicus GLO-30 heights are egm96)")
    datum_text = y.scalar(m["vertical_datum"], "dtm.vertical_datum", "ellipsoid or egm96")
    try:
        datum = VerticalDatum(datum_text)
    except ValueError:
        y.fail(m["vertical_datum"], f"dtm.vertical_datum is {_show(str(datum_text))}",
               "ellipsoid (WGS84 heights) or egm96 (heights above the EGM96 geoid)")
    crs = None
    if "crs" in m:
        crs = y.text(m["crs"], "dtm.crs")
        from pyproj import CRS
        from pyproj.exceptions import CRSError

        try:
            CRS.from_user_input(crs)
        except CRSError:
            y.fail(m["crs"], f"dtm.crs {_show(crs)} is not a CRS PROJ knows",
                   "a CRS such as EPSG:4326 or EPSG:32652")
    margin, spacing = (y.bounded(m[key], f"dtm.{key}") if key in m else None
                       for key in ("margin_m", "spacing_m"))
    return DtmConfig(paths[0], sigma_h, (0.0, 0.0, 0.0), tuple(paths[1:]), datum, crs, margin,
                     spacing, **offset_sigmas)


def _intrinsics(y: _Yaml, node: yaml.Node, width: int, height: int
                ) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy, each within sense for the image size."""
    values = y.vector(node, "camera.intrinsics", (4,))
    side = max(width, height)
    lo_f, hi_f = (k * side for k in FOCAL_RANGE_SIDES)
    m = PRINCIPAL_POINT_MARGIN_SIDES
    bounds = {"fx": (lo_f, hi_f), "fy": (lo_f, hi_f),
              "cx": (-m * width, (1 + m) * width), "cy": (-m * height, (1 + m) * height)}
    for i, (name, (lo, hi)) in enumerate(bounds.items()):
        value = float(values[i])
        if not lo <= value <= hi:
            y.fail(node.value[i], f"camera.intrinsics {name} is {value!r}",
                   f"{name} in [{lo:g}, {hi:g}] px for a {width}x{height} image (focal "
                   f"lengths {FOCAL_RANGE_SIDES[0]:g}-{FOCAL_RANGE_SIDES[1]:g} image sides, "
                   f"principal point at most {m:g} image sides outside the image)")
    fx, fy, cx, cy = values.tolist()
    return fx, fy, cx, cy


def _parse_camera(y: _Yaml, node: yaml.Node, line: int) -> CameraConfig:
    pairs = y.pairs(node, "camera", line)
    m = y.keys(pairs, "camera", line,
               ("resolution", "intrinsics", "pixel_sigma_px", "body_T_cam"),
               ("distortion_model", "distortion_coeffs", "time_offset_s", "calibration",
                "principal_point_sigma_px"))
    res_node = m["resolution"]
    if not isinstance(res_node, yaml.SequenceNode) or len(res_node.value) != 2:
        y.fail(res_node, "camera.resolution is not two values", "[width, height] in pixels")
    width = y.integer(res_node.value[0], "camera.resolution width")
    height = y.integer(res_node.value[1], "camera.resolution height")
    lo_px, hi_px = RESOLUTION_RANGE_PX
    if not (lo_px <= width <= hi_px and lo_px <= height <= hi_px):
        y.fail(res_node, f"camera.resolution is {width}x{height}",
               f"[width, height], each from {lo_px} to {hi_px} px")
    fx, fy, cx, cy = _intrinsics(y, m["intrinsics"], width, height)

    model, distortion = _distortion(y, m)
    try:
        camera = PinholeCamera(width, height, fx, fy, cx, cy, distortion, model)
    except ValueError as exc:
        y.fail(m["intrinsics"], f"invalid camera: {exc}",
               "positive focal lengths fx, fy and a finite principal point cx, cy")
    sigma = y.bounded(m["pixel_sigma_px"], "camera.pixel_sigma_px")

    mount_line = y.line(pairs["body_T_cam"][0])
    mount = y.keys(y.pairs(m["body_T_cam"], "camera.body_T_cam", mount_line),
                   "camera.body_T_cam", mount_line, ("translation_m", "quaternion_wxyz"))
    translation = y.vector(mount["translation_m"], "camera.body_T_cam.translation_m", (3,),
                           True)
    quat = y.quaternion(mount["quaternion_wxyz"], "camera.body_T_cam.quaternion_wxyz")
    offset_s = (y.bounded(m["time_offset_s"], "camera.time_offset_s")
                if "time_offset_s" in m else 0.0)
    calibration = (_calibration_sigmas(y, m["calibration"], y.line(pairs["calibration"][0]))
                   if "calibration" in m else None)
    principal_point_sigma = (y.bounded(m["principal_point_sigma_px"],
                                       "camera.principal_point_sigma_px")
                             if "principal_point_sigma_px" in m else None)
    return CameraConfig(camera, sigma, make_pose(quat_wxyz_to_rotation(quat), translation),
                        offset_s, calibration, principal_point_sigma)


def _calibration_sigmas(y: _Yaml, node: yaml.Node, line: int) -> CalibrationSigmas:
    """``camera.calibration``: the prior sigmas of the calibration estimated online."""
    names = ("time_offset_sigma_s", "mount_sigma_deg", "focal_scale_sigma")
    m = y.keys(y.pairs(node, "camera.calibration", line), "camera.calibration", line, names)
    return CalibrationSigmas(*(y.bounded(m[k], f"camera.calibration.{k}") for k in names))


#: What ``camera.distortion_coeffs`` holds for each model (docs/flightlog.md, camera).
_COEFFS_EXPECTED = {
    DistortionModel.RADTAN: "[k1, k2, p1, p2] or [k1, k2, p1, p2, k3]",
    DistortionModel.EQUIDISTANT: "[k1, k2, k3, k4]",
}


def _distortion(y: _Yaml, m: dict[str, yaml.Node]
                ) -> tuple[DistortionModel, tuple[float, ...]]:
    """``camera.distortion_model`` and ``camera.distortion_coeffs``, checked together."""
    model_node = m.get("distortion_model")
    name = None if model_node is None else y.value(model_node)
    if name is None or name == "none":
        if "distortion_coeffs" in m:
            y.fail(m["distortion_coeffs"], "distortion_coeffs given without a distortion model",
                   "camera.distortion_model: radtan or equidistant, or no distortion_coeffs")
        return DistortionModel.NONE, ()
    assert model_node is not None
    try:
        model = DistortionModel(name)
    except ValueError:
        model = None
    if model is None or model is DistortionModel.NONE:
        y.fail(model_node, f"distortion_model {_show(str(name))} is not supported",
               "radtan (OpenCV k1 k2 p1 p2 [k3]), equidistant (OpenCV fisheye k1 k2 k3 k4) "
               "or none")
    if "distortion_coeffs" not in m:
        y.fail(model_node, f"distortion_model {model.value} without distortion_coeffs",
               f"camera.distortion_coeffs: {_COEFFS_EXPECTED[model]}")
    coeffs = y.vector(m["distortion_coeffs"], "camera.distortion_coeffs",
                      DISTORTION_LENGTHS[model], True)
    return model, tuple(coeffs.tolist())


_IMU_KEYS = ("rate_hz", "gyroscope_noise_density", "accelerometer_noise_density",
             "gyroscope_random_walk", "accelerometer_random_walk")


def _parse_imu(y: _Yaml, node: yaml.Node, line: int) -> ImuConfig:
    m = y.keys(y.pairs(node, "imu", line), "imu", line, _IMU_KEYS)
    # Zero noise would make the IMU factors' information infinite: RANGES keeps it positive.
    return ImuConfig(*(y.bounded(m[key], f"imu.{key}") for key in _IMU_KEYS))


_INITIAL_VECTORS = (("position_m", 3), ("quaternion_wxyz", 4), ("velocity_mps", 3),
                    ("gyro_bias", 3), ("accel_bias", 3))
_INITIAL_SIGMAS = ("sigma_position_m", "sigma_attitude_deg", "sigma_velocity_mps",
                   "sigma_gyro_bias", "sigma_accel_bias")


def _parse_initial_state(y: _Yaml, node: yaml.Node, line: int,
                         origin: GeodeticOrigin | None) -> InitialState:
    vectors = tuple(name for name, _ in _INITIAL_VECTORS)
    pairs = y.pairs(node, "initial_state", line)
    geodetic = any(key in pairs for key in _ORIGIN_KEYS)
    if geodetic:
        if origin is None:
            key = next(key for key in _ORIGIN_KEYS if key in pairs)
            y.fail(pairs[key][0], f"initial_state.{key} without a geodetic origin",
                   "a top-level origin: (latitude_deg, longitude_deg, height_m), or "
                   "initial_state.position_m in the world frame")
        if "position_m" in pairs:
            y.fail(pairs["position_m"][0], "initial_state has both position_m and "
                   "latitude_deg/longitude_deg/height_m", "one of the two")
        required = _ORIGIN_KEYS + vectors[1:] + _INITIAL_SIGMAS
    else:
        required = vectors + _INITIAL_SIGMAS
    m = y.keys(pairs, "initial_state", line, required)
    values: dict[str, Any] = {}
    for name, n in _INITIAL_VECTORS:
        if name in m:
            dotted = f"initial_state.{name}"
            values[name] = (y.quaternion(m[name], dotted) if name == "quaternion_wxyz"
                            else y.vector(m[name], dotted, (n,), True))
    for name in _INITIAL_SIGMAS:
        values[name] = y.bounded(m[name], f"initial_state.{name}")
    if geodetic:
        assert origin is not None
        lat, lon, h = (y.number(m[key], f"initial_state.{key}") for key in _ORIGIN_KEYS)
        if not -90.0 <= lat <= 90.0:
            y.fail(m["latitude_deg"], f"initial_state.latitude_deg is {lat!r}",
                   "a WGS84 latitude in degrees, -90 to 90")
        try:
            position, quat, velocity = local_frame(origin).states_from_geodetic(
                lat, lon, h, values["quaternion_wxyz"], values["velocity_mps"])
        except CdtmError as exc:
            y.fail(m["latitude_deg"], f"initial_state: {exc}", "a geodetic position")
        values["position_m"], values["quaternion_wxyz"], values["velocity_mps"] = (
            position[0], quat[0], velocity[0])
    return InitialState(**values)
