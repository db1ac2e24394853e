"""A EuRoC/ASL ``mav0`` folder as a sensor recording (``cdtm import euroc``).

The folder (https://projects.asl.ethz.ch/datasets/doku.php?id=kmavvisualinertialdatasets)::

    mav0/imu0/data.csv                      #timestamp [ns], w_RS_S (3, rad/s), a_RS_S (3, m/s^2)
    mav0/imu0/sensor.yaml                   T_BS, rate_hz, the four noise densities
    mav0/cam0/data.csv                      #timestamp [ns], filename
    mav0/cam0/data/<filename>               the images
    mav0/cam0/sensor.yaml                   T_BS, resolution, intrinsics, distortion
    mav0/state_groundtruth_estimate0/data.csv   optional: t, p, q (w first), v, b_w, b_a

The body is the IMU (EuRoC's convention: the IMU's ``T_BS`` is the identity), so the
camera's mounting is ``inv(T_BS_imu) T_BS_cam``. A Kalibr camchain (``T_cam_imu``,
``timeshift_cam_imu``) and IMU file replace the sensor.yaml files when given.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from cdtm_graph.errors import SensorDataError, why_not_a_file
from cdtm_graph.flightlog.model import FlightLog, ImuConfig
from cdtm_graph.flightlog.problems import _fail, _show
from cdtm_graph.flightlog.tables import _read_frames, _read_imu
from cdtm_graph.geometry import invert_pose
from cdtm_graph.importers.calibration import (
    CameraCalibration,
    read_euroc_sensor,
    read_kalibr_camchain,
    read_kalibr_imu,
)
from cdtm_graph.importers.recording import (
    IMAGE_DIR,
    ImportSettings,
    SensorRecording,
    assemble_flightlog,
    check_prior,
    image_size_px,
    read_groundtruth,
    write_imported_log,
)

#: The IMU's T_BS may differ from the identity by this much (EuRoC prints 1.0 and 0.0).
IDENTITY_TOL = 1e-9


@dataclass(frozen=True)
class EurocFolder:
    """The files of one camera and one IMU of a ``mav0`` folder."""

    mav0: Path
    camera: str = "cam0"
    imu: str = "imu0"

    @property
    def imu_csv(self) -> Path:
        return self.mav0 / self.imu / "data.csv"

    @property
    def imu_yaml(self) -> Path:
        return self.mav0 / self.imu / "sensor.yaml"

    @property
    def frames_csv(self) -> Path:
        return self.mav0 / self.camera / "data.csv"

    @property
    def camera_yaml(self) -> Path:
        return self.mav0 / self.camera / "sensor.yaml"

    @property
    def image_dir(self) -> Path:
        return self.mav0 / self.camera / "data"

    @property
    def groundtruth_csv(self) -> Path:
        return self.mav0 / "state_groundtruth_estimate0" / "data.csv"


def find_mav0(path: str | os.PathLike) -> Path:
    """The ``mav0`` folder of a EuRoC sequence given as ``mav0`` itself or its parent.

    Raises:
        SensorDataError: neither holds the folders of one.
    """
    path = Path(path)
    for candidate in (path, path / "mav0"):
        if (candidate / "imu0").is_dir() or (candidate / "cam0").is_dir():
            return candidate
    raise SensorDataError(f"{path}: not a EuRoC folder; expected mav0/ (or the folder holding "
                          "it) with imu0/data.csv, cam0/data.csv and cam0/data/")


def read_euroc(path: str | os.PathLike, *, kalibr: str | os.PathLike | None = None,
               kalibr_imu: str | os.PathLike | None = None, camera: str = "cam0",
               imu: str = "imu0") -> tuple[SensorRecording, list[Path]]:
    """Read a EuRoC folder's IMU, frame stamps, calibration and ground truth.

    Args:
        path: the ``mav0`` folder or the sequence folder holding it.
        kalibr: a Kalibr camchain to use instead of ``cam0/sensor.yaml``.
        kalibr_imu: a Kalibr IMU file to use instead of ``imu0/sensor.yaml``.
        camera, imu: which sensors (``cam0``, ``imu0``).

    Returns:
        The recording, and the image file of each frame.

    Raises:
        FlightLogError: a CSV or YAML file is malformed (file, line, expected).
        SensorDataError: a required file is missing; an image is missing, or the first
            does not fit the calibration's resolution (a wrong camera or camchain: a
            later image of another size is named by ``cdtm track``, which reads them all).
    """
    folder = EurocFolder(find_mav0(path), camera, imu)
    for required in (folder.imu_csv, folder.frames_csv):
        if not required.is_file():
            raise SensorDataError(f"{required}: {why_not_a_file(required)}; expected a EuRoC "
                                  f"folder with {imu}/data.csv and {camera}/data.csv")
    imu_samples = _read_imu(folder.imu_csv, str(folder.imu_csv))
    stamps, first_line = _read_frames(folder.frames_csv, str(folder.frames_csv))
    images = _image_files(folder, stamps.image, first_line)

    imu_body_T_sensor = np.eye(4)
    if folder.imu_yaml.is_file():
        imu_sensor = read_euroc_sensor(folder.imu_yaml, "imu")
        imu_body_T_sensor = imu_sensor.body_T_sensor
    if kalibr_imu is not None:
        calibration = read_kalibr_imu(kalibr_imu, imu)
        imu_config = calibration.imu
    elif folder.imu_yaml.is_file():
        noise = imu_sensor.imu_noise
        assert noise is not None
        imu_config = ImuConfig(imu_sensor.rate_hz, *noise)
    else:
        raise SensorDataError(f"{folder.imu_yaml}: missing; expected the IMU's noise model "
                              "there, or --kalibr-imu IMU_YAML")

    if kalibr is not None:
        cam = read_kalibr_camchain(kalibr, camera)
    elif folder.camera_yaml.is_file():
        sensor = read_euroc_sensor(folder.camera_yaml, "camera")
        assert sensor.camera is not None
        imu_T_body = invert_pose(imu_body_T_sensor)
        cam = CameraCalibration(sensor.camera, imu_T_body @ sensor.body_T_sensor)
    else:
        raise SensorDataError(f"{folder.camera_yaml}: missing; expected the camera's "
                              "calibration there, or --kalibr CAMCHAIN")
    _check_image_size(images[0], cam, folder.frames_csv, first_line)

    groundtruth = bias = None
    if folder.groundtruth_csv.is_file():
        if not np.allclose(imu_body_T_sensor, np.eye(4), rtol=0.0, atol=IDENTITY_TOL):
            raise SensorDataError(
                f"{folder.imu_yaml}: T_BS is not the identity, so the ground truth (of the "
                "body B) is not the IMU's; expected EuRoC's convention, the IMU as the body")
        groundtruth, bias = read_groundtruth(folder.groundtruth_csv, None)
    provenance = {"format": "euroc", "camera": camera, "imu": imu,
                  "calibration": str(kalibr) if kalibr is not None else
                  str(folder.camera_yaml),
                  "imu_noise": str(kalibr_imu) if kalibr_imu is not None else
                  str(folder.imu_yaml)}
    recording = SensorRecording(str(path), imu_samples, stamps.t_ns, cam, imu_config,
                                groundtruth, bias, provenance)
    return recording, images


def import_euroc(path: str | os.PathLike, directory: str | os.PathLike,
                 final_dir: str | os.PathLike, settings: ImportSettings, *,
                 kalibr: str | os.PathLike | None = None,
                 kalibr_imu: str | os.PathLike | None = None, camera: str = "cam0",
                 imu: str = "imu0",
                 progress: Callable[[int, int], None] | None = None) -> FlightLog:
    """Read a EuRoC folder and write it as a flight log into ``directory`` (a staging
    directory published as ``final_dir``): images copied into ``images/``.

    Returns:
        The log as written and read back.
    """
    recording, sources = read_euroc(path, kalibr=kalibr, kalibr_imu=kalibr_imu, camera=camera,
                                    imu=imu)
    check_prior(settings, recording.groundtruth is not None, recording.source)
    directory = Path(directory)
    source_of = {f"{IMAGE_DIR}/{source.name}": source for source in sources}
    log = assemble_flightlog(recording, tuple(source_of), settings)  # before the copying
    (directory / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(log.frames.image):
        shutil.copyfile(source_of[name], directory / name)
        if progress is not None:
            progress(k + 1, len(log.frames))
    return write_imported_log(log, settings, directory, final_dir)


def _image_files(folder: EurocFolder, names: tuple[str, ...], first_line: int) -> list[Path]:
    shown = str(folder.frames_csv)
    files = []
    row_of: dict[str, int] = {}
    for k, name in enumerate(names):
        parts = PurePosixPath(name).parts
        if not name or len(parts) != 1 or name in (".", ".."):
            _fail(shown, first_line + k, f"filename {_show(name)}",
                  f"a file name in {folder.image_dir}")
        if name in row_of:
            _fail(shown, first_line + k, f"image {_show(name)} is named again (first on line "
                  f"{first_line + row_of[name]})", "one image file per row")
        row_of[name] = k
        path = folder.image_dir / name
        if not path.is_file():
            _fail(shown, first_line + k, f"image {_show(name)} {why_not_a_file(path)} in "
                  f"{folder.image_dir}", "an image file for every row")
        files.append(path)
    return files


def _check_image_size(image: Path, cam: CameraCalibration, shown: Path, line: int) -> None:
    """The first image has the calibration's resolution (a wrong camera or camchain)."""
    width, height = image_size_px(image)
    c = cam.camera
    if (width, height) != (c.width, c.height):
        _fail(str(shown), line, f"image {image.name} is {width}x{height} px but the "
              f"calibration says {c.width}x{c.height}", "images of the calibrated camera")
