"""The CSV files of a flight log: imu.csv, frames.csv, tracks.csv, nav.csv, groundtruth.csv.

Large files (hours of 200 Hz IMU) are parsed by numpy's C reader; only when that fails does
a line-by-line scan run, to find and name the offending line.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.flightlog.model import (
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    NAV_CSV,
    QUATERNION_EXACT_TOL,
    QUATERNION_UNIT_TOL,
    TRACKS_CSV,
    Frames,
    ImuSamples,
    States,
    Tracks,
)
from cdtm_graph.flightlog.problems import _fail, _first, _Problems, _show

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1

#: Observations up to this far outside the image (px) are kept as they are: detectors
#: and sub-pixel refinement put corners a fraction of a pixel past the border (measured:
#: 4 of 8953 observations 0.05-0.35 px outside a 640x480 image). Kept, not clamped:
#: clamping would move them; the camera model (pinhole, radtan undistortion checked by
#: reprojection) holds a few pixels past the border. Farther out is a data error.
IMAGE_BORDER_MARGIN_PX = 2.0

#: Largest magnitude of a CSV value in sense, per column group: far beyond any sensor or
#: flight (gyros saturate near 70 rad/s, accelerometers near 200 g), so a value past it is
#: a unit or format mistake; it would overflow in preintegration or the C-DTM noise.
IMU_GYRO_MAX_RADPS = 1e3
IMU_ACC_MAX_MPS2 = 1e4
#: Positions (m; UTM-sized coordinates allowed) and velocities (m/s) of nav.csv and
#: groundtruth.csv, as flight.yaml's initial state.
STATE_POSITION_MAX_M = 1e8
STATE_VELOCITY_MAX_MPS = 1e4
_CHUNK_BYTES = 1 << 24
#: Bytes read to find the first line (a header is short; a longer line is data).
_HEADER_PROBE_BYTES = 1 << 16

@dataclass(frozen=True)
class _CsvSpec:
    """Columns of one CSV file: integer columns first, then float columns."""

    name: str
    int_columns: tuple[str, ...]
    float_columns: tuple[str, ...]
    extra_columns_ignored: bool = False

    @property
    def columns(self) -> tuple[str, ...]:
        return self.int_columns + self.float_columns

    @property
    def expected_row(self) -> str:
        more = " (further columns ignored)" if self.extra_columns_ignored else ""
        return f"{len(self.columns)} comma-separated values {','.join(self.columns)}{more}"


_STATE_COLUMNS = ("px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz")
#: nav.csv / groundtruth.csv with a header naming these columns hold geodetic states:
#: WGS84 latitude, longitude, ellipsoidal height, and the attitude (body -> local ENU) and
#: velocity (east, north, up) in the local ENU at each position. Needs a geodetic origin.
_GEODETIC_STATE_COLUMNS = ("latitude_deg", "longitude_deg", "height_m", "qw", "qx", "qy",
                           "qz", "ve", "vn", "vu")
_IMU_SPEC = _CsvSpec(IMU_CSV, ("t_ns",),
                     ("gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z"))
_TRACKS_SPEC = _CsvSpec(TRACKS_CSV, ("frame", "track_id"), ("u", "v"))
_NAV_SPEC = _CsvSpec(NAV_CSV, ("t_ns",), _STATE_COLUMNS)
_GROUNDTRUTH_SPEC = _CsvSpec(GROUNDTRUTH_CSV, ("t_ns",), _STATE_COLUMNS,
                             extra_columns_ignored=True)
_FRAMES_COLUMNS = ("t_ns", "image")
_FRAMES_EXPECTED = "2 comma-separated values t_ns,image; image may be empty"


@dataclass(frozen=True)
class _Table:
    """Parsed numeric CSV: row i was line ``first_line + i`` of the file."""

    ints: np.ndarray    # (N, n_int) int64
    floats: np.ndarray  # (N, n_float) float64
    first_line: int


def _is_header(first_line: str) -> bool:
    """A first line is a header when it does not parse as numbers.

    Only the first field decides: a header's first field is a name (EuRoC's
    ``#timestamp [ns]``), while a data row with one bad value further right is a
    malformed row to report, not a line to skip silently.
    """
    first_field = first_line.split(",", 1)[0].strip()
    try:
        float(first_field)
    except ValueError:
        return True
    return False


@dataclass(frozen=True)
class _LineCount:
    has_header: bool
    data_lines: int      # lines after the header, as a text editor counts them
    plain_newlines: bool  # only '\n' or '\r\n' line ends: numpy's row i is line i


def _first_line_is_header(path: Path, shown: str) -> bool:
    """Whether the file's first line (ended by \n, \r\n or \r) is a header; False if empty."""
    with path.open("rb") as f:
        head = f.read(_HEADER_PROBE_BYTES)
    lines = head.splitlines()
    if not lines:
        return False
    try:
        text = lines[0].decode("utf-8-sig")
    except UnicodeDecodeError:
        if len(lines) == 1 and len(head) == _HEADER_PROBE_BYTES:
            text = ""  # a cut multi-byte character at the probe's end: the line is long
        else:
            _fail(shown, 1, "the first line is not UTF-8 text", "a UTF-8 CSV file")
    return _is_header(text)


def _count_lines(path: Path, shown: str) -> _LineCount:
    """Count lines as ``bytes.splitlines`` splits them: ``\n``, ``\r\n`` and a lone ``\r``
    (classic Mac OS files) each end one line."""
    has_header = _first_line_is_header(path, shown)
    with path.open("rb") as f:
        first = f.readline()  # up to the first \n: the whole file if its lines end in \r
        newlines = first.count(b"\n")
        carriage_returns = first.count(b"\r")
        crlf = first.count(b"\r\n")
        last = first[-1:]
        size = len(first)
        previous_last = first[-1:]
        while chunk := f.read(_CHUNK_BYTES):
            newlines += chunk.count(b"\n")
            if b"\r" in chunk or previous_last == b"\r":  # rare: skip two scans otherwise
                carriage_returns += chunk.count(b"\r")
                crlf += chunk.count(b"\r\n") + (previous_last == b"\r" and chunk[:1] == b"\n")
            last = previous_last = chunk[-1:]
            size += len(chunk)
    lone_returns = carriage_returns - crlf
    total = newlines + lone_returns + (1 if size and last not in (b"\n", b"\r") else 0)
    return _LineCount(has_header, max(total - int(has_header), 0), lone_returns == 0)


def _read_numeric_csv(path: Path, shown: str, spec: _CsvSpec) -> _Table:
    """Parse a numeric CSV: numpy's C reader when the file is clean, else a line scan."""
    count = _count_lines(path, shown)
    first_line = 2 if count.has_header else 1
    n_int, n_float = len(spec.int_columns), len(spec.float_columns)
    if count.data_lines == 0:
        return _Table(np.zeros((0, n_int), np.int64), np.zeros((0, n_float)), first_line)
    dtype = np.dtype([("i", np.int64, (n_int,)), ("f", np.float64, (n_float,))])
    usecols = range(n_int + n_float) if spec.extra_columns_ignored else None
    rows = None
    if count.plain_newlines:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = np.loadtxt(path, delimiter=",", dtype=dtype, comments=None,
                                  skiprows=int(count.has_header), usecols=usecols,
                                  encoding="utf-8-sig", ndmin=1)
        except (ValueError, UnicodeDecodeError):
            rows = None
    # numpy skips blank lines, which would shift every later line number: only a
    # row count equal to the line count proves row i is line first_line + i.
    if rows is None or rows.shape[0] != count.data_lines:
        return _scan_numeric_csv(path, shown, spec, count.has_header)
    return _Table(np.ascontiguousarray(rows["i"]), np.ascontiguousarray(rows["f"]), first_line)


def _split_lines(path: Path, shown: str, has_header: bool) -> Iterable[tuple[int, str]]:
    """(line number, text) of each data line, decoding line by line to name bad bytes."""
    data = path.read_bytes()
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    lines = data.splitlines()  # \n, \r\n and \r, as numpy and text editors split
    for index in range(int(has_header), len(lines)):
        try:
            text = lines[index].decode("utf-8")
        except UnicodeDecodeError:
            _fail(shown, index + 1, "the line is not UTF-8 text", "a UTF-8 CSV file")
        yield index + 1, text


def _parse_int(token: str) -> int | None:
    text = token.strip()
    if "_" in text:  # Python's int() accepts 1_000; the format does not
        return None
    try:
        value = int(text, 10)
    except ValueError:
        return None
    return value if _INT64_MIN <= value <= _INT64_MAX else None


def _parse_float(token: str) -> float | None:
    text = token.strip()
    if "_" in text:
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _split_row(shown: str, line_no: int, text: str, n_columns: int, columns: Sequence[str],
               expected: str, extra_ignored: bool) -> list[str]:
    if not text.strip():
        _fail(shown, line_no, "empty line", expected)
    tokens = text.split(",")
    if len(tokens) < n_columns:
        _fail(shown, line_no,
              f"short row: {len(tokens)} value{'s' if len(tokens) != 1 else ''}, "
              f"no {columns[len(tokens)]}", expected)
    if len(tokens) > n_columns and not extra_ignored:
        _fail(shown, line_no, f"{len(tokens)} values, {len(tokens) - n_columns} too many",
              expected)
    return tokens


def _scan_numeric_csv(path: Path, shown: str, spec: _CsvSpec, has_header: bool) -> _Table:
    """The slow, exact path: parse line by line; the first bad line raises."""
    columns = spec.columns
    n_int = len(spec.int_columns)
    ints: list[list[int]] = []
    floats: list[list[float]] = []
    first_line = 2 if has_header else 1
    for line_no, text in _split_lines(path, shown, has_header):
        tokens = _split_row(shown, line_no, text, len(columns), columns, spec.expected_row,
                            spec.extra_columns_ignored)
        row_ints = []
        for j in range(n_int):
            value = _parse_int(tokens[j])
            if value is None:
                _fail(shown, line_no, f"{columns[j]} is {_show(tokens[j].strip())}",
                      f"an integer ({spec.expected_row})")
            row_ints.append(value)
        row_floats = []
        for j in range(n_int, len(columns)):
            number = _parse_float(tokens[j])
            if number is None:
                _fail(shown, line_no, f"{columns[j]} is {_show(tokens[j].strip())}, not a number",
                      f"a number ({spec.expected_row})")
            row_floats.append(number)
        ints.append(row_ints)
        floats.append(row_floats)
    return _Table(np.array(ints, dtype=np.int64).reshape(-1, n_int),
                  np.array(floats, dtype=float).reshape(-1, len(columns) - n_int), first_line)


def _check_finite(problems: _Problems, table: _Table, spec: _CsvSpec) -> None:
    bad = ~np.isfinite(table.floats)
    row = _first(bad.any(axis=1))
    if row is not None:
        col = int(np.flatnonzero(bad[row])[0])
        problems.add(row, f"{spec.float_columns[col]} is {float(table.floats[row, col])!r}",
                     "a finite number (no NaN or inf)")


def _check_magnitude(problems: _Problems, table: _Table, spec: _CsvSpec, columns: slice,
                     limit: float, unit: str) -> None:
    """The first row with a finite value beyond ``limit`` in the given float columns."""
    block = table.floats[:, columns]
    with np.errstate(invalid="ignore"):
        bad = np.abs(block) > limit  # NaN compares False: _check_finite reports it
    row = _first(bad.any(axis=1))
    if row is not None:
        col = int(np.flatnonzero(bad[row])[0])
        name = spec.float_columns[columns][col]
        problems.add(row, f"{name} is {float(block[row, col])!r}",
                     f"|{name}| <= {limit:g} {unit}")


def _check_increasing(problems: _Problems, t_ns: np.ndarray, name: str = "t_ns") -> None:
    step = np.diff(t_ns)
    row = _first(step <= 0)
    if row is not None:
        problems.add(row + 1, f"{name} {int(t_ns[row + 1])} is not after the previous row's "
                     f"{int(t_ns[row])}", f"strictly increasing {name}")


def _checked_quaternions(problems: _Problems, quat: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(quat, axis=1)
    off = np.abs(norm - 1.0)
    problems.check(~(off <= QUATERNION_UNIT_TOL),
                   lambda r: f"quaternion qw,qx,qy,qz has norm {norm[r]:.6g}",
                   f"a unit quaternion (|norm - 1| <= {QUATERNION_UNIT_TOL:g})")
    # (only the rows that pass: a zero one is a problem, not a division by zero)
    fix = (off > QUATERNION_EXACT_TOL) & (off <= QUATERNION_UNIT_TOL)
    if np.any(fix):
        quat = quat.copy()
        quat[fix] /= norm[fix, None]
    return quat


def _header_names(path: Path) -> list[str]:
    """Column names of a header line ('#' and spaces stripped, lower case), or []."""
    with path.open("rb") as f:
        first = f.readline()
    try:
        text = first.decode("utf-8-sig").rstrip("\r\n")
    except UnicodeDecodeError:
        return []
    if not text or not _is_header(text):
        return []
    return [name.strip().lstrip("#").strip().lower() for name in text.split(",")]


def _geodetic_spec(spec: _CsvSpec) -> _CsvSpec:
    return _CsvSpec(spec.name, spec.int_columns, _GEODETIC_STATE_COLUMNS,
                    spec.extra_columns_ignored)


def _is_geodetic_states(path: Path) -> bool:
    """True when the header names latitude_deg, longitude_deg, height_m after the time."""
    return _header_names(path)[1:4] == list(_GEODETIC_STATE_COLUMNS[:3])


def _read_states(path: Path, shown: str, spec: _CsvSpec) -> tuple[States, int]:
    """States as the file holds them: for a geodetic file (:func:`_is_geodetic_states`)
    ``position_m`` holds latitude, longitude and height and the rest is local ENU."""
    geodetic = _is_geodetic_states(path)
    if geodetic:
        spec = _geodetic_spec(spec)
    table = _read_numeric_csv(path, shown, spec)
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, spec)
    _check_magnitude(problems, table, spec, slice(0, 3), STATE_POSITION_MAX_M, "m")
    _check_magnitude(problems, table, spec, slice(7, 10), STATE_VELOCITY_MAX_MPS, "m/s")
    t_ns = table.ints[:, 0]
    _check_increasing(problems, t_ns)
    finite = np.isfinite(table.floats).all(axis=1)
    quat = table.floats[:, 3:7]
    quat = np.where(finite[:, None], quat, 1.0)  # NaN rows are already reported
    quat = _checked_quaternions(problems, quat)
    if geodetic:
        lat = np.where(finite, table.floats[:, 0], 0.0)
        problems.check(np.abs(lat) > 90.0,
                       lambda r: f"latitude_deg is {float(lat[r])!r}",
                       "a WGS84 latitude in degrees, -90 to 90")
    problems.raise_first()
    states = States(t_ns.copy(), table.floats[:, 0:3].copy(), quat, table.floats[:, 7:10].copy())
    return states, table.first_line


def _read_imu(path: Path, shown: str) -> ImuSamples:
    table = _read_numeric_csv(path, shown, _IMU_SPEC)
    if table.ints.shape[0] == 0:
        _fail(shown, table.first_line, "no IMU samples", _IMU_SPEC.expected_row)
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, _IMU_SPEC)
    _check_magnitude(problems, table, _IMU_SPEC, slice(0, 3), IMU_GYRO_MAX_RADPS, "rad/s")
    _check_magnitude(problems, table, _IMU_SPEC, slice(3, 6), IMU_ACC_MAX_MPS2, "m/s^2")
    _check_increasing(problems, table.ints[:, 0])
    problems.raise_first()
    return ImuSamples(table.ints[:, 0].copy(), table.floats[:, 0:3].copy(),
                      table.floats[:, 3:6].copy())


def _read_frames(path: Path, shown: str) -> tuple[Frames, int]:
    """frames.csv: small (one row per frame), so a plain line loop is fast enough."""
    has_header = _first_line_is_header(path, shown)
    first_line = 2 if has_header else 1
    times: list[int] = []
    images: list[str] = []
    for line_no, text in _split_lines(path, shown, has_header):
        tokens = _split_row(shown, line_no, text, 2, _FRAMES_COLUMNS, _FRAMES_EXPECTED, False)
        value = _parse_int(tokens[0])
        if value is None:
            _fail(shown, line_no, f"t_ns is {_show(tokens[0].strip())}",
                  f"integer nanoseconds in {_FRAMES_EXPECTED}")
        times.append(value)
        images.append(tokens[1].strip())
    if not times:
        _fail(shown, first_line, "no frames", _FRAMES_EXPECTED)
    t_ns = np.array(times, dtype=np.int64)
    problems = _Problems(shown, first_line)
    _check_increasing(problems, t_ns)
    problems.raise_first()
    return Frames(t_ns, tuple(images)), first_line


def _read_tracks(path: Path, shown: str, n_frames: int, camera: PinholeCamera) -> Tracks:
    spec = _TRACKS_SPEC
    table = _read_numeric_csv(path, shown, spec)
    frame, track_id = table.ints[:, 0], table.ints[:, 1]
    uv = table.floats
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, spec)
    problems.check((frame < 0) | (frame >= n_frames),
                   lambda r: f"frame {int(frame[r])} does not exist "
                             f"({FRAMES_CSV} has {n_frames} frames)",
                   f"a 0-based row index of {FRAMES_CSV}: 0 <= frame <= {n_frames - 1}")
    problems.check(np.concatenate([[False], np.diff(frame) < 0]),
                   lambda r: f"frame {int(frame[r])} comes after frame {int(frame[r - 1])}",
                   "rows sorted by frame")
    # A track seen twice in one frame: report the later row of each duplicate pair.
    order = np.lexsort((np.arange(len(frame)), frame, track_id))
    dup = (track_id[order[1:]] == track_id[order[:-1]]) & (frame[order[1:]] == frame[order[:-1]])
    later = order[1:][dup]
    if later.size:
        row = int(later.min())
        problems.add(row, f"track {int(track_id[row])} is seen twice in frame {int(frame[row])}",
                     "each track at most once per frame")
    finite = np.isfinite(uv).all(axis=1)
    margin = IMAGE_BORDER_MARGIN_PX
    lo_u, hi_u = -0.5 - margin, camera.width - 0.5 + margin
    lo_v, hi_v = -0.5 - margin, camera.height - 0.5 + margin
    problems.check(finite & ~camera.in_image(uv, margin_px=margin),
                   lambda r: f"pixel (u, v) = ({float(uv[r, 0])!r}, {float(uv[r, 1])!r}) is "
                             f"outside the {camera.width}x{camera.height} image by more than "
                             f"the {margin:g} px border margin",
                   f"{lo_u:g} <= u <= {hi_u:g} and {lo_v:g} <= v <= {hi_v:g}")
    problems.raise_first()
    return Tracks(frame.copy(), track_id.copy(), uv.copy())


def _check_nav_times(nav: States, frames: Frames, shown: str, first_line: int) -> None:
    k_nav, k_frames = len(nav), len(frames)
    expected = f"one row per frame, with the times of {FRAMES_CSV} ({k_frames} rows)"
    n = min(k_nav, k_frames)
    row = _first(nav.t_ns[:n] != frames.t_ns[:n])
    if row is not None:
        _fail(shown, first_line + row,
              f"t_ns {int(nav.t_ns[row])} is not the time of frame {row} "
              f"({int(frames.t_ns[row])})", expected)
    if k_nav < k_frames:
        _fail(shown, first_line + k_nav, f"{k_nav} rows for {k_frames} frames: "
              f"no row for frame {k_nav} (t_ns {int(frames.t_ns[k_nav])})", expected)
    if k_nav > k_frames:
        _fail(shown, first_line + k_frames, f"{k_nav} rows for {k_frames} frames: "
              f"this row is beyond the last frame", expected)


