"""IMU faults: gaps, a rate unlike flight.yaml's, stuck and saturated values, found and named.

Pure: sample arrays in, named findings out (no I/O, no GTSAM). What each fault means and
what the estimator does about it:

- ``imu_gap``: consecutive samples more than ``IMU_GAP_PERIODS`` nominal periods apart
  (``1 / imu.rate_hz``). The IMU model (:mod:`cdtm_graph.imu`) holds the samples on
  either side across the gap, as always, but gives those pieces the noise of a maneuver
  model (:class:`~cdtm_graph.imu.GapNoise`), so the preintegration's covariance says how
  little it knows there. The same formula, :func:`gap_after`, marks gaps for both.
- ``imu_rate_mismatch``: the median sample spacing is more than ``RATE_TOLERANCE`` from
  ``1 / imu.rate_hz``: a wrong rate in flight.yaml or timestamps in the wrong unit. The
  preintegration uses continuous-time noise densities and the samples' own times, so the
  estimate does not depend on ``rate_hz``; only the gap threshold does.
- ``imu_stuck``: all six values exactly repeated for at least ``STUCK_MIN_SAMPLES``
  consecutive samples: a driver re-sending its last message, a frozen sensor. A real
  sensor in flight never repeats all six to the last bit (noise, vibration); a noiseless
  synthetic log may, and is named too.
- ``imu_saturated``: one channel sitting at its own extreme value over the stream for at
  least ``SATURATION_MIN_SAMPLES`` consecutive samples (the flat top of a clipped
  signal), or at or beyond a range the caller gives.
- ``imu_time_order``: a timestamp not after the previous one. The flight-log reader
  already refuses such an ``imu.csv`` (one line naming the row) and so does the live feed
  (``ImuFeed``): a repeated timestamp is ambiguous (which of the two rows is right?) and
  usually means a logger fault worth seeing before a run. This check names it for arrays
  that come from elsewhere.

The estimator does not drop stuck or saturated samples (it names them and the frames
they touch); it models gaps. :func:`finding_frames` and :func:`finding_flags` map findings
to frames: a fault over ``[first_t_ns, last_t_ns]`` touches frame k >= 1 when the IMU
interval ``[t_k-1, t_k]`` that predicts it overlaps the fault.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdtm_graph.codes import Code
from cdtm_graph.constants import NS_PER_S
from cdtm_graph.imu import IMU_GAP_PERIODS, gap_threshold_ns

#: The median spacing may differ from 1 / rate_hz by this fraction (clock drift and
#: rounding of real IMUs is far below 1%).
RATE_TOLERANCE = 0.05
#: All six values repeated for this many consecutive samples (50 ms at 200 Hz) is stuck.
STUCK_MIN_SAMPLES = 10
#: A channel at its extreme value for this many consecutive samples is clipped: with any
#: noise a true maximum is reached once.
SATURATION_MIN_SAMPLES = 3
#: At most this many findings per code; the last one then also covers the rest.
MAX_FINDINGS_PER_CODE = 20


#: What a finding is about (its ``code`` in report.json), in the order findings are listed.
IMU_FAULTS = (Code.IMU_GAP, Code.IMU_RATE_MISMATCH, Code.IMU_STUCK, Code.IMU_SATURATED,
              Code.IMU_TIME_ORDER)


@dataclass(frozen=True)
class ImuFinding:
    """One fault of an IMU stream.

    Attributes:
        code: which fault.
        message: one line for a person: what, where, what was expected.
        first_t_ns, last_t_ns: the samples (times, ns) the fault spans, inclusive: for a
            gap the last sample before it and the first after it.
    """

    code: Code  # one of IMU_FAULTS
    message: str
    first_t_ns: int
    last_t_ns: int

    def frames(self, frame_t_ns: np.ndarray) -> tuple[int, int] | None:
        """The first and last frame it touches (:func:`finding_frames`)."""
        return finding_frames(self.first_t_ns, self.last_t_ns, frame_t_ns)

    def to_dict(self, frame_t_ns: np.ndarray | None = None) -> dict:
        """Plain values for report.json; with frame times, also ``first_frame`` and
        ``last_frame`` (None when it touches no frame interval)."""
        out: dict = {"code": self.code.value, "message": self.message,
                     "first_t_ns": int(self.first_t_ns), "last_t_ns": int(self.last_t_ns)}
        if frame_t_ns is not None:
            span = self.frames(frame_t_ns)
            out["first_frame"], out["last_frame"] = span if span is not None else (None, None)
        return out


@dataclass(frozen=True)
class MeasuredImuNoise:
    """The white noise the samples themselves show, against flight.yaml's densities.

    Each channel's scatter from sample to sample, as a continuous-time density: the
    second differences ``x[i+1] - 2 x[i] + x[i-1]`` of white noise of density ``n`` at
    spacing ``dt`` have variance ``6 n^2 / dt``, while a flight's motion, smooth over a
    few samples, adds next to nothing to them (its second derivative times ``dt^2``). A
    robust scale (the MAD) keeps single spikes out. Vibration counts: it is in the samples
    the preintegration integrates. An IMU that filters its output before sampling reads
    low, never high.

    Attributes:
        gyro_density, accel_density: (3,) measured, rad/s/sqrt(Hz) and m/s^2/sqrt(Hz).
        stated_gyro_density, stated_accel_density: flight.yaml's ``imu.*_noise_density``.
    """

    gyro_density: np.ndarray
    accel_density: np.ndarray
    stated_gyro_density: float
    stated_accel_density: float

    @property
    def ratios(self) -> tuple[float, float]:
        """Measured over stated, gyro and accelerometer (the median axis of each)."""
        return (float(np.median(self.gyro_density)) / self.stated_gyro_density,
                float(np.median(self.accel_density)) / self.stated_accel_density)

    def to_dict(self) -> dict:
        return {"gyro_density": [float(v) for v in self.gyro_density],
                "accel_density": [float(v) for v in self.accel_density],
                "stated_gyro_density": self.stated_gyro_density,
                "stated_accel_density": self.stated_accel_density,
                "measured_over_stated": list(self.ratios)}


def sample_noise(t_ns: np.ndarray, gyro_radps: np.ndarray, acc_mps2: np.ndarray,
                 stated_gyro_density: float, stated_accel_density: float
                 ) -> MeasuredImuNoise | None:
    """:class:`MeasuredImuNoise` of a sample stream (None with fewer than 10 samples)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size < 10:
        return None
    dt_s = float(np.median(np.diff(t))) / NS_PER_S

    def density(x: np.ndarray) -> np.ndarray:
        d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
        mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
        return 1.4826 * mad * np.sqrt(dt_s / 6.0)

    return MeasuredImuNoise(density(np.asarray(gyro_radps, float)),
                            density(np.asarray(acc_mps2, float)),
                            float(stated_gyro_density), float(stated_accel_density))


@dataclass(frozen=True)
class ImuCheckSettings:
    """Thresholds of :func:`check_imu` (module docstring for the defaults' reasons).

    Attributes:
        gap_periods: a gap is a spacing above this many nominal periods.
        rate_tolerance: relative difference of the median spacing from ``1 / rate_hz``.
        stuck_min_samples: consecutive identical samples (all six values) that are stuck.
        saturation_min_samples: consecutive samples of a channel at its extreme that are
            clipped.
        gyro_range_radps, accel_range_mps2: the sensor's full scale, if known: a value at
            or beyond it is saturated whatever its run.
    """

    gap_periods: float = IMU_GAP_PERIODS
    rate_tolerance: float = RATE_TOLERANCE
    stuck_min_samples: int = STUCK_MIN_SAMPLES
    saturation_min_samples: int = SATURATION_MIN_SAMPLES
    gyro_range_radps: float | None = None
    accel_range_mps2: float | None = None


def imu_gaps(frame_t_ns: np.ndarray, imu_t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stretches without an IMU sample in each frame's interval (from the previous
    frame; none for the first frame).

    Returns:
        ``(inside_s, whole_s)``, (K,) each: the longest such stretch within the interval,
        and the whole length of that stretch (also where it spans several frames).
    """
    frame_t_ns = np.asarray(frame_t_ns, dtype=np.int64)
    imu_t_ns = np.asarray(imu_t_ns, dtype=np.int64)
    k = frame_t_ns.size
    inside, whole = np.zeros(k), np.zeros(k)
    if k < 2 or imu_t_ns.size == 0:
        return inside, whole
    # the stretches between samples, and before the first and after the last one
    edges = np.concatenate([[min(int(imu_t_ns[0]), int(frame_t_ns[0]))], imu_t_ns,
                            [max(int(imu_t_ns[-1]), int(frame_t_ns[-1]))]])
    starts, ends = edges[:-1], edges[1:]
    for j in range(1, k):
        t0, t1 = int(frame_t_ns[j - 1]), int(frame_t_ns[j])
        lo = int(np.searchsorted(ends, t0, side="right"))
        hi = int(np.searchsorted(starts, t1, side="left"))
        if hi > lo:
            span = np.minimum(ends[lo:hi], t1) - np.maximum(starts[lo:hi], t0)
            i = int(np.argmax(span))
            inside[j] = span[i] / NS_PER_S
            whole[j] = (ends[lo + i] - starts[lo + i]) / NS_PER_S
    return inside, whole


def finding_frames(first_t_ns: int, last_t_ns: int,
                   frame_t_ns: np.ndarray) -> tuple[int, int] | None:
    """The frames a fault over ``[first_t_ns, last_t_ns]`` touches.

    Frame k >= 1 is touched when its IMU interval ``[t_k-1, t_k]`` overlaps the fault by
    more than a point: the IMU factor into frame k (and its prediction) used the faulty
    samples. A fault that is a single instant touches the interval holding it.

    Args:
        first_t_ns, last_t_ns: the fault's span, ns.
        frame_t_ns: (K,) frame times, increasing.

    Returns:
        ``(first_frame, last_frame)``, or None if it lies outside every frame interval.
    """
    t = np.asarray(frame_t_ns, dtype=np.int64)
    if t.size < 2:
        return None
    a, b = int(first_t_ns), int(last_t_ns)
    if b < a:
        a, b = b, a
    if a == b:
        touched = (t[:-1] <= a) & (t[1:] >= a)
    else:
        touched = (t[:-1] < b) & (t[1:] > a)
    k = np.flatnonzero(touched)
    if k.size == 0:
        return None
    return int(k[0]) + 1, int(k[-1]) + 1


def finding_flags(findings: list[ImuFinding], frame_t_ns: np.ndarray) -> dict[str, np.ndarray]:
    """Per code, which frames the findings touch: ``{"imu_gap": (K,) bool, ...}`` (codes
    without findings left out)."""
    k = np.asarray(frame_t_ns).shape[0]
    flags: dict[str, np.ndarray] = {}
    for f in findings:
        span = f.frames(frame_t_ns)
        if span is None:
            continue
        flag = flags.setdefault(f.code.value, np.zeros(k, dtype=bool))
        flag[span[0]:span[1] + 1] = True
    return flags


def check_imu(t_ns: np.ndarray, gyro_radps: np.ndarray, acc_mps2: np.ndarray, rate_hz: float,
              settings: ImuCheckSettings | None = None) -> list[ImuFinding]:
    """Every fault of an IMU sample stream, named (module docstring).

    Args:
        t_ns: (N,) sample times, ns.
        gyro_radps: (N, 3) angular rate. acc_mps2: (N, 3) specific force.
        rate_hz: flight.yaml's ``imu.rate_hz``.
        settings: thresholds.

    Returns:
        The findings, by code in :data:`IMU_FAULTS` order, then by time.
    """
    settings = settings or ImuCheckSettings()
    t = np.asarray(t_ns, dtype=np.int64)
    values = np.column_stack([np.asarray(gyro_radps, dtype=float),
                              np.asarray(acc_mps2, dtype=float)])
    if t.ndim != 1 or values.shape != (t.size, 6):
        raise ValueError(f"gyro and acc must be (N, 3) for t_ns of shape {t.shape}, got "
                         f"{np.shape(gyro_radps)} and {np.shape(acc_mps2)}")
    findings: list[ImuFinding] = []
    if t.size < 2:
        return findings
    dt = np.diff(t)
    findings += _gaps(t, dt, rate_hz, settings.gap_periods)
    findings += _rate(t, dt, rate_hz, settings.rate_tolerance)
    stuck = _stuck_samples(values, settings.stuck_min_samples)
    findings += _cap([ImuFinding(
        Code.IMU_STUCK, f"IMU: all six values repeat unchanged over {b - a + 1} samples "
        f"from t = {t[a]} ns to {t[b]} ns ({(t[b] - t[a]) / 1e6:.1f} ms); expected a "
        "sensor's values to vary from sample to sample (a frozen sensor or a driver "
        "re-sending its last message)", int(t[a]), int(t[b])) for a, b in _runs(stuck)])
    findings += _saturated(t, values, stuck, settings)
    findings += _cap([ImuFinding(
        Code.IMU_TIME_ORDER, f"IMU: t_ns {t[i + 1]} is not after the previous sample's "
        f"{t[i]}; expected strictly increasing times", int(t[i]), int(t[i + 1]))
        for i in np.flatnonzero(dt <= 0)])
    return findings


# --------------------------------------------------------------------------- pieces


_CHANNELS = ("gyro x", "gyro y", "gyro z", "acc x", "acc y", "acc z")
_UNITS = ("rad/s",) * 3 + ("m/s^2",) * 3


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) indices of each run of True."""
    m = np.r_[False, np.asarray(mask, dtype=bool), False]
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]


def _cap(findings: list[ImuFinding]) -> list[ImuFinding]:
    """At most ``MAX_FINDINGS_PER_CODE``; the last kept then spans the rest too."""
    if len(findings) <= MAX_FINDINGS_PER_CODE:
        return findings
    kept = findings[:MAX_FINDINGS_PER_CODE - 1]
    rest = findings[MAX_FINDINGS_PER_CODE - 1:]
    first = rest[0]
    kept.append(ImuFinding(first.code, f"{first.message} (and {len(rest) - 1} more like it "
                           f"up to t = {rest[-1].last_t_ns} ns)", first.first_t_ns,
                           rest[-1].last_t_ns))
    return kept


def _gaps(t: np.ndarray, dt: np.ndarray, rate_hz: float, periods: float) -> list[ImuFinding]:
    gap = dt > gap_threshold_ns(rate_hz, periods)
    out = []
    for a, b in _runs(gap):  # consecutive gaps (isolated samples between them) are one
        missing = float(np.sum(dt[a:b + 1])) / NS_PER_S
        n = b - a + 1
        spacing = (f"a spacing of {dt[a] / 1e6:.1f} ms" if n == 1 else
                   f"{n} spacings of {dt[a:b + 1].min() / 1e6:.1f}-{dt[a:b + 1].max() / 1e6:.1f}"
                   " ms")
        out.append(ImuFinding(
            Code.IMU_GAP, f"IMU gap: {missing:.3f} s from t = {t[a]} ns to {t[b + 1]} ns "
            f"({spacing}); expected samples every {1e3 / rate_hz:.3g} ms (imu.rate_hz "
            f"{rate_hz:g}), at most {periods:g} periods apart: the motion there is modelled "
            "as unknown within a maneuver's bounds", int(t[a]), int(t[b + 1])))
    return _cap(out)


def _rate(t: np.ndarray, dt: np.ndarray, rate_hz: float, tolerance: float) -> list[ImuFinding]:
    positive = dt[dt > 0]
    if positive.size == 0:
        return []
    measured_hz = NS_PER_S / float(np.median(positive))
    if abs(measured_hz / rate_hz - 1.0) <= tolerance:
        return []
    return [ImuFinding(
        Code.IMU_RATE_MISMATCH, f"IMU: samples come at {measured_hz:.4g} Hz (median spacing "
        f"{1e3 / measured_hz:.4g} ms); flight.yaml says imu.rate_hz {rate_hz:g}: expected "
        f"them within {100 * tolerance:g}% (a wrong rate, or times in another unit)",
        int(t[0]), int(t[-1]))]


def _stuck_samples(values: np.ndarray, min_samples: int) -> np.ndarray:
    """(N,) bool: samples inside a run of at least ``min_samples`` identical ones."""
    same = np.all(values[1:] == values[:-1], axis=1)
    stuck = np.zeros(values.shape[0], dtype=bool)
    for a, b in _runs(same):  # samples a .. b+1 are identical
        if b - a + 2 >= min_samples:
            stuck[a:b + 2] = True
    return stuck


def _saturated(t: np.ndarray, values: np.ndarray, stuck: np.ndarray,
               settings: ImuCheckSettings) -> list[ImuFinding]:
    out = []
    ranges = [settings.gyro_range_radps] * 3 + [settings.accel_range_mps2] * 3
    for c in range(6):
        v = values[:, c]
        hi, lo = float(np.max(v)), float(np.min(v))
        at = np.zeros(v.size, dtype=bool)
        if hi > lo:  # a constant channel has no flat top (stuck names a frozen sensor)
            for extreme in (hi, lo):
                for a, b in _runs(v == extreme):
                    if b - a + 1 >= settings.saturation_min_samples:
                        at[a:b + 1] = True
        if ranges[c] is not None:
            at |= np.abs(v) >= ranges[c]
        at &= ~stuck
        for a, b in _runs(at):
            limit = (f"at or beyond the range {ranges[c]:g} {_UNITS[c]}"
                     if ranges[c] is not None and abs(v[a]) >= ranges[c] else
                     "at its extreme value over the stream")
            out.append(ImuFinding(
                Code.IMU_SATURATED, f"IMU {_CHANNELS[c]} is {v[a]:.6g} {_UNITS[c]}, {limit}, "
                f"over {b - a + 1} samples from t = {t[a]} ns to {t[b]} ns; expected a "
                "signal inside the sensor's range (a clipped value says too little)",
                int(t[a]), int(t[b])))
    out.sort(key=lambda f: f.first_t_ns)
    return _cap(out)
