"""Calibration files of the sensor world: Kalibr's camchain and IMU YAML, EuRoC's sensor.yaml.

Read node by node, as flight.yaml is (:mod:`cdtm_graph.flightlog.config`), so every problem is
one line ``<file>:<line>: <what>; expected <what>``. Keys these readers do not use are
ignored (Kalibr writes many: ``cam_overlaps``, ``T_cn_cnm1``...). The names are Kalibr's
(https://github.com/ethz-asl/kalibr/wiki/yaml-formats) and EuRoC's (ASL dataset format):

* camchain: ``camN: {camera_model: pinhole, intrinsics: [fu, fv, pu, pv], distortion_model:
  radtan | equidistant | none, distortion_coeffs, resolution: [w, h], T_cam_imu (4x4, rows),
  timeshift_cam_imu (s; t_imu = t_cam + shift), rostopic}``;
* IMU: ``{accelerometer_noise_density, accelerometer_random_walk, gyroscope_noise_density,
  gyroscope_random_walk, update_rate, rostopic}``, at the top or under ``imuN:``;
* EuRoC ``sensor.yaml``: ``T_BS: {rows: 4, cols: 4, data: [16, row-major]}`` (the sensor in
  the body frame), ``rate_hz``, and for a camera ``resolution``, ``camera_model``,
  ``intrinsics``, ``distortion_model`` (``radial-tangential`` or ``equidistant``),
  ``distortion_coefficients``; for an IMU the four noise keys.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from cdtm_graph.camera import DISTORTION_LENGTHS, DistortionModel, PinholeCamera
from cdtm_graph.errors import why_not_a_file
from cdtm_graph.flightlog.config import RANGES, _Yaml
from cdtm_graph.flightlog.model import ImuConfig
from cdtm_graph.flightlog.problems import _fail, _fail_path, _show
from cdtm_graph.geometry import invert_pose, make_pose

#: A transform's rotation may be this far from orthonormal (max |R^T R - I|): printed
#: calibrations carry 6-10 digits; further off is a wrong matrix, not rounding.
ROTATION_ORTHONORMAL_TOL = 1e-3

#: Distortion model names of Kalibr and EuRoC, and what they are here.
DISTORTION_NAMES = {
    "radtan": DistortionModel.RADTAN,
    "radial-tangential": DistortionModel.RADTAN,
    "plumb_bob": DistortionModel.RADTAN,
    "equidistant": DistortionModel.EQUIDISTANT,
    "none": DistortionModel.NONE,
}

_IMU_NOISE_KEYS = ("gyroscope_noise_density", "accelerometer_noise_density",
                   "gyroscope_random_walk", "accelerometer_random_walk")


@dataclass(frozen=True)
class CameraCalibration:
    """One camera's calibration, in this project's terms.

    Attributes:
        camera: intrinsics and lens.
        body_T_cam: (4, 4) the camera in the body (IMU) frame (Kalibr's ``T_cam_imu``
            inverted; EuRoC's ``T_BS`` of the camera after the IMU's).
        time_offset_s: ``t_imu = t_cam + time_offset_s`` (Kalibr's ``timeshift_cam_imu``).
        rostopic: the image topic the calibration names, or None.
    """

    camera: PinholeCamera
    body_T_cam: np.ndarray
    time_offset_s: float = 0.0
    rostopic: str | None = None


@dataclass(frozen=True)
class ImuCalibration:
    """An IMU's noise model and rate (``imu.*`` of flight.yaml) and its topic."""

    imu: ImuConfig
    rostopic: str | None = None


class _SensorYaml(_Yaml):
    """A calibration file walked node by node (keys not used are ignored)."""

    def mapping(self, node: yaml.Node, name: str, line: int) -> dict[str, yaml.Node]:
        return {key: value for key, (_, value) in self.pairs(node, name, line).items()}

    def need(self, m: dict[str, yaml.Node], key: str, parent: str, line: int,
             expected: str) -> yaml.Node:
        if key not in m:
            self.fail(line, f"missing key '{key}'" + (f" in {parent}" if parent else ""),
                      expected)
        return m[key]

    def matrix4(self, node: yaml.Node, name: str) -> np.ndarray:
        """A 4x4 rigid transform as 4 rows of 4 numbers, or EuRoC's {rows, cols, data}."""
        if isinstance(node, yaml.MappingNode):
            m = self.mapping(node, name, self.line(node))
            values = self.vector(self.need(m, "data", name, self.line(node),
                                           f"{name}.data: 16 numbers, row-major"),
                                 f"{name}.data", (16,))
            matrix = values.reshape(4, 4)
        elif isinstance(node, yaml.SequenceNode) and len(node.value) == 4:
            matrix = np.array([self.vector(row, f"{name}[{i}]", (4,))
                               for i, row in enumerate(node.value)])
        else:
            self.fail(node, f"{name} is not a 4x4 matrix",
                      "4 rows of 4 numbers, or {rows: 4, cols: 4, data: [16 numbers]}")
        return self.rigid(node, name, matrix)

    def rigid(self, node: yaml.Node, name: str, matrix: np.ndarray) -> np.ndarray:
        if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
            self.fail(node, f"{name} has last row {matrix[3].tolist()}", "[0, 0, 0, 1]")
        R = matrix[:3, :3]
        off = float(np.abs(R.T @ R - np.eye(3)).max())
        if not off <= ROTATION_ORTHONORMAL_TOL or np.linalg.det(R) < 0:
            self.fail(node, f"{name}'s rotation is not a rotation (max |R^T R - I| = {off:.3g}, "
                      f"det {np.linalg.det(R):.3g})",
                      f"an orthonormal rotation with det +1 (to {ROTATION_ORTHONORMAL_TOL:g})")
        # The nearest rotation (polar decomposition): printed digits leave ~1e-9 of skew.
        u, _, vt = np.linalg.svd(R)
        return make_pose(u @ vt, matrix[:3, 3])

    def optional_text(self, m: dict[str, yaml.Node], key: str) -> str | None:
        return self.text(m[key], key).strip() if key in m else None


def _open(path: str | os.PathLike) -> tuple[_SensorYaml, yaml.Node]:
    """The document node of a YAML calibration file (OpenCV's ``%YAML:1.0`` line tolerated)."""
    path = Path(path)
    shown = str(path)
    if not path.is_file():
        _fail_path(shown, why_not_a_file(path), "a YAML calibration file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        _fail(shown, 1, "not UTF-8 text", "a UTF-8 YAML file")
    # OpenCV FileStorage writes '%YAML:1.0', which is not a YAML directive: blank it (the
    # line stays, so line numbers still count from the file's top).
    text = re.sub(r"\A%YAML:\s*1\.\d+[^\n]*", "", text)
    loader = yaml.SafeLoader(text)
    y = _SensorYaml(shown, loader)
    try:
        document = loader.get_single_node()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        _fail(shown, mark.line + 1 if mark else 1, f"YAML error: {problem}", "valid YAML")
    if document is None:
        _fail(shown, 1, "empty file", "a YAML mapping")
    return y, document


@contextlib.contextmanager
def _yaml_errors(y: _SensorYaml) -> Iterator[None]:
    """Constructor errors (an unknown !tag) while values are read, as one-line errors."""
    try:
        yield
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        _fail(y.shown, mark.line + 1 if mark else 1, f"YAML error: {problem}", "valid YAML")


def _camera(y: _SensorYaml, m: dict[str, yaml.Node], name: str, line: int, *,
            coeffs_key: str) -> PinholeCamera:
    """Pinhole intrinsics, resolution and lens of a Kalibr camera or a EuRoC sensor.yaml."""
    if "camera_model" in m:
        model_name = y.scalar(m["camera_model"], f"{name}camera_model", "pinhole")
        if model_name != "pinhole":
            y.fail(m["camera_model"], f"{name}camera_model {_show(str(model_name))} is not "
                   "supported", "pinhole (with radtan, equidistant or no distortion)")
    res_node = y.need(m, "resolution", name, line, "resolution: [width, height] in pixels")
    if not isinstance(res_node, yaml.SequenceNode) or len(res_node.value) != 2:
        y.fail(res_node, f"{name}resolution is not two values", "[width, height] in pixels")
    width = y.integer(res_node.value[0], f"{name}resolution width")
    height = y.integer(res_node.value[1], f"{name}resolution height")
    intrinsics = y.vector(y.need(m, "intrinsics", name, line, "intrinsics: [fu, fv, pu, pv]"),
                          f"{name}intrinsics", (4,))
    lens = DistortionModel.NONE
    coeffs: tuple[float, ...] = ()
    if (("distortion_model" not in m or y.value(m["distortion_model"]) is None)
            and coeffs_key in m and any(v != 0 for v in (y.value(m[coeffs_key]) or [0]))):
        y.fail(m[coeffs_key], f"{name}{coeffs_key} without a distortion_model",
               "distortion_model: radtan (radial-tangential) or equidistant beside them")
    if "distortion_model" in m and y.value(m["distortion_model"]) is not None:
        text = str(y.value(m["distortion_model"]))
        if text not in DISTORTION_NAMES:
            y.fail(m["distortion_model"], f"{name}distortion_model {_show(text)} is not "
                   "supported", f"one of {', '.join(DISTORTION_NAMES)}")
        lens = DISTORTION_NAMES[text]
    if lens is not DistortionModel.NONE:
        node = y.need(m, coeffs_key, name, line, f"{coeffs_key} for {lens.value}")
        coeffs = tuple(y.vector(node, f"{name}{coeffs_key}", DISTORTION_LENGTHS[lens]).tolist())
        limit = RANGES["camera.distortion_coeffs"]
        if not all(limit.lo <= c <= limit.hi for c in coeffs):
            y.fail(node, f"{name}{coeffs_key} is {list(coeffs)}", f"each {limit}")
        if lens is DistortionModel.RADTAN and len(coeffs) == 5 and coeffs[4] == 0.0:
            coeffs = coeffs[:4]
        if lens is DistortionModel.RADTAN and not any(coeffs):
            # zeros: no distortion (an equidistant lens with zeros is still theta, not tan)
            lens, coeffs = DistortionModel.NONE, ()
    fx, fy, cx, cy = intrinsics.tolist()
    try:
        return PinholeCamera(width, height, fx, fy, cx, cy, coeffs, lens)
    except ValueError as exc:
        y.fail(m["intrinsics"], f"invalid camera: {exc}", "positive focal lengths")


def read_kalibr_camchain(path: str | os.PathLike, camera: str = "cam0") -> CameraCalibration:
    """One camera of a Kalibr camchain (``camchain.yaml`` or ``camchain-imucam.yaml``).

    Args:
        path: the camchain file.
        camera: which camera (``cam0``, ``cam1``, ...).

    Returns:
        The calibration; ``body_T_cam`` is ``T_cam_imu`` inverted (the body is the IMU).

    Raises:
        FlightLogError: the file, the camera or a key is missing or malformed; a camera
            model other than pinhole, a lens other than radtan, equidistant or none.
    """
    y, document = _open(path)
    with _yaml_errors(y):
        top = y.mapping(document, "", 1)
        if camera not in top:
            cams = ", ".join(k for k in top if k.startswith("cam")) or "none"
            _fail(y.shown, 1, f"no camera '{camera}' (cameras here: {cams})",
                  "a Kalibr camchain holding that camera")
        cam_node = top[camera]
        line = y.line(cam_node)
        m = y.mapping(cam_node, camera, line)
        prefix = f"{camera}."
        lens = _camera(y, m, prefix, line, coeffs_key="distortion_coeffs")
        node = y.need(m, "T_cam_imu", prefix, line,
                      f"{prefix}T_cam_imu (from kalibr_calibrate_imu_camera: the camchain-"
                      "imucam file)")
        cam_T_imu = y.matrix4(node, f"{prefix}T_cam_imu")
        shift = 0.0
        if "timeshift_cam_imu" in m:
            shift = y.bounded(m["timeshift_cam_imu"], "camera.time_offset_s")
        return CameraCalibration(lens, invert_pose(cam_T_imu), shift,
                                 y.optional_text(m, "rostopic"))


#: Kalibr's results-cam.txt: a camera's block opens ``camN (topic):``, and its
#: ``projection: [fu fv pu pv] +- [...]`` line gives the estimates and their 1-sigma (the
#: square roots of its estimator's covariance diagonal, kalibr_camera_calibration's
#: ``recoverCovariance``), numpy-printed, possibly over several lines.
_RESULTS_BLOCK = re.compile(r"^\s*(cam\d+)\s*\(.*\):\s*$")
_RESULTS_PROJECTION = re.compile(r"projection:\s*\[([^\]]*)\]\s*\+-\s*\[([^\]]*)\]")


def read_kalibr_principal_point_sigma(path: str | os.PathLike, camera: str = "cam0"
                                      ) -> float:
    """How well Kalibr's camera calibration tells one camera's principal point: the larger
    of the 1-sigmas of ``pu`` and ``pv`` (px) in its ``results-cam.txt``
    (``kalibr_calibrate_cameras``).

    Raises:
        FlightLogError: the file is missing or not text, holds no block for ``camera``, or
            its ``projection`` line is not four values ``+-`` four positive ones.
    """
    path = Path(path)
    shown = str(path)
    if not path.is_file():
        _fail_path(shown, why_not_a_file(path), "Kalibr's results-cam.txt")
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError:
        _fail(shown, 1, "not UTF-8 text", "Kalibr's results-cam.txt")
    blocks = [(i, m.group(1)) for i, line in enumerate(lines)
              if (m := _RESULTS_BLOCK.match(line))]
    start = next((i for i, name in blocks if name == camera), None)
    if start is None:
        cams = ", ".join(name for _, name in blocks) or "none"
        _fail(shown, 1, f"no block for camera '{camera}' (cameras here: {cams})",
              "Kalibr's results-cam.txt (kalibr_calibrate_cameras), with a "
              "'cam0 (topic):' block")
    end = next((i for i, _ in blocks if i > start), len(lines))
    at = next((i for i in range(start, end) if "projection:" in lines[i]), None)
    if at is None:
        _fail(shown, start + 1, f"camera '{camera}' has no 'projection:' line",
              "'projection: [fu fv pu pv] +- [sigmas]'")
    text = " ".join(lines[at:min(at + 4, end)])  # (numpy may wrap a long array)
    match = _RESULTS_PROJECTION.search(text)
    values: list[float] = []
    if match is not None:
        with contextlib.suppress(ValueError):
            values = [float(v) for v in (match.group(1) + " " + match.group(2)).split()]
    sigmas = np.asarray(values[4:], dtype=float)
    if len(values) != 8 or not (np.all(np.isfinite(values)) and np.all(sigmas > 0)):
        _fail(shown, at + 1, f"projection line {_show(lines[at].strip())}",
              "'projection: [fu fv pu pv] +- [sigmas]', four numbers and four positive "
              "sigmas (a pinhole camera)")
    sigma = float(max(sigmas[2], sigmas[3]))
    limit = RANGES["camera.principal_point_sigma_px"]
    if sigma > limit.hi:
        _fail(shown, at + 1, f"camera '{camera}''s principal point sigma {sigma:g} px",
              f"at most {limit.hi:g} px (camera.principal_point_sigma_px): a calibration")
    return sigma


def read_kalibr_imu(path: str | os.PathLike, imu: str = "imu0") -> ImuCalibration:
    """A Kalibr IMU file (``imu.yaml``, or ``imu-...yaml`` with ``imu0:`` sections).

    The noise keys are Kalibr's names and units (continuous-time densities), as flight.yaml's
    ``imu:``; the rate is ``update_rate`` (Hz).

    Raises:
        FlightLogError: a key is missing, not a number, or outside flight.yaml's range.
    """
    y, document = _open(path)
    with _yaml_errors(y):
        top = y.mapping(document, "", 1)
        line, prefix, m = 1, "", top
        if imu in top:
            line = y.line(top[imu])
            prefix = f"{imu}."
            m = y.mapping(top[imu], imu, line)
        noise = _imu_noise(y, m, prefix, line)
        rate = y.bounded(y.need(m, "update_rate", prefix, line, "update_rate: the IMU rate (Hz)"),
                         "imu.rate_hz")
        return ImuCalibration(ImuConfig(rate, *noise), y.optional_text(m, "rostopic"))


def _imu_noise(y: _SensorYaml, m: dict[str, yaml.Node], prefix: str, line: int
               ) -> tuple[float, float, float, float]:
    values = []
    for key in _IMU_NOISE_KEYS:
        node = y.need(m, key, prefix, line, f"the IMU noise keys {', '.join(_IMU_NOISE_KEYS)}")
        values.append(y.bounded(node, f"imu.{key}"))
    return values[0], values[1], values[2], values[3]


@dataclass(frozen=True)
class EurocSensor:
    """A EuRoC ``sensor.yaml``: the sensor in the body frame and its rate.

    Attributes:
        body_T_sensor: (4, 4) ``T_BS``.
        rate_hz: ``rate_hz``.
        camera: a camera's intrinsics and lens, or None for an IMU.
        imu_noise: an IMU's four noise densities (flight.yaml order), or None.
    """

    body_T_sensor: np.ndarray
    rate_hz: float
    camera: PinholeCamera | None = None
    imu_noise: tuple[float, float, float, float] | None = None


def read_euroc_sensor(path: str | os.PathLike, kind: str) -> EurocSensor:
    """A EuRoC/ASL ``sensor.yaml`` of a camera (``kind="camera"``) or an IMU (``"imu"``).

    Raises:
        FlightLogError: a key is missing or malformed.
    """
    y, document = _open(path)
    with _yaml_errors(y):
        m = y.mapping(document, "", 1)
        body_T_sensor = y.matrix4(y.need(m, "T_BS", "", 1, "T_BS: the sensor in the body frame"),
                                  "T_BS")
        rate_node = y.need(m, "rate_hz", "", 1, "rate_hz: the sensor's rate (Hz)")
        rate = (y.number(rate_node, "rate_hz", positive=True) if kind == "camera"
                else y.bounded(rate_node, "imu.rate_hz"))
        if kind == "camera":
            camera = _camera(y, m, "", 1, coeffs_key="distortion_coefficients")
            return EurocSensor(body_T_sensor, rate, camera=camera)
        return EurocSensor(body_T_sensor, rate, imu_noise=_imu_noise(y, m, "", 1))

