"""A simulated flight path with exact kinematics: position, attitude and their derivatives.

The path is a chain of straight legs and level coordinated turns at constant altitude
and ground speed. Every quantity the IMU senses is evaluated analytically at any time,
so simulated IMU samples and camera frame times agree with the true state to round-off.

Frames and conventions (docs/flightlog.md): ``world`` is local ENU (metres, z up), ``body``
is the IMU frame, here x forward, y left, z up. Quaternions are Hamilton, w first, and
rotate body vectors into world. The attitude is ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

Smoothness. A turn does not start abruptly: its heading rate rises from zero to the
plan's turn rate along a raised-cosine ramp (``bank_ramp_s``), holds, and falls back the
same way. The bank angle follows the turn rate (coordinated turn,
``tan(bank) = speed * heading_rate / g``). The cosine ramp has zero slope at both ends,
so the heading rate is C1, the roll rate (which follows its slope) is continuous, and so
are the world acceleration and the body angular rate. Only their slopes jump at ramp
ends (a kink), which costs a discrete integrator O(dt^2) once, not O(dt).

Closed form. Heading, heading rate, velocity, acceleration, attitude and body angular
rate are closed-form in every segment. Position is closed-form on straights and
constant-rate arcs; inside a ramp, ``integral cos(heading)`` has no elementary
antiderivative and is evaluated by Gauss-Legendre quadrature of the closed-form
integrand, which is analytic with a small heading change, so it is exact to round-off
(``tests/sim/test_trajectory.py`` checks it against adaptive quadrature). Nothing is
numerically differentiated.

Times outside the plan: before t = 0 the first straight is extended backwards, after
the last leg the aircraft flies straight on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from cdtm_graph.constants import STANDARD_GRAVITY_MPS2
from cdtm_graph.geometry import quat_wxyz_to_rotation

# Gauss-Legendre nodes for the position inside a turn-rate ramp. The integrand
# cos(heading0 + d(s)) has d(s) <= turn_rate * ramp / 2 (0.05 rad at the defaults, and
# < 1 rad for any sane plan); 24 nodes integrate it to ~1e-15 relative.
_RAMP_QUADRATURE_NODES = 24
_GL_X, _GL_W = np.polynomial.legendre.leggauss(_RAMP_QUADRATURE_NODES)


@dataclass(frozen=True)
class FlightPlan:
    """Straight legs joined by coordinated level turns at constant altitude and speed.

    Attributes:
        start_xy_m: world (x, y) of the body at t = 0, metres.
        altitude_m: world z of the body, metres (constant).
        speed_mps: ground speed, m/s (constant, > 0).
        heading_deg: initial course, degrees from +x (east) towards +y (north).
        legs: ``(straight length m, then turn angle deg)`` per leg; a positive turn
            is to the left (counter-clockwise seen from above), 0 means no turn.
        turn_rate_dps: heading rate in a turn once the ramp is done, deg/s (> 0).
        bank_ramp_s: duration of the raised-cosine ramp of the heading rate (and so of
            the bank angle) at the entry and at the exit of every turn, s. 0 gives an
            instantaneous bank onset: the angular rate and acceleration then jump.
            A turn too small to reach ``turn_rate_dps`` within two ramps peaks lower.
        gravity_mps2: gravity magnitude used for the coordinated bank angle only.
        camera_wobble_deg: amplitude of a smooth sinusoidal roll and pitch perturbation
            added to the attitude, degrees (0 = none). It tilts the body (and camera)
            off the velocity so attitude is not constant on straights; the path itself
            is unchanged.
        camera_wobble_period_s: period of the roll wobble, s; the pitch wobble runs at
            sqrt(2) times this period so the two never lock into a fixed pattern.
    """

    start_xy_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 1000.0
    speed_mps: float = 200.0
    heading_deg: float = 0.0
    legs: tuple[tuple[float, float], ...] = ((2000.0, 90.0), (2000.0, -90.0), (2000.0, 0.0))
    turn_rate_dps: float = 3.0
    bank_ramp_s: float = 2.0
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    camera_wobble_deg: float = 0.0
    camera_wobble_period_s: float = 10.0

    def __post_init__(self) -> None:
        if not self.speed_mps > 0:
            raise ValueError(f"speed_mps must be > 0, got {self.speed_mps}")
        if not self.turn_rate_dps > 0:
            raise ValueError(f"turn_rate_dps must be > 0, got {self.turn_rate_dps}")
        if not self.bank_ramp_s >= 0:
            raise ValueError(f"bank_ramp_s must be >= 0, got {self.bank_ramp_s}")
        if not self.gravity_mps2 > 0:
            raise ValueError(f"gravity_mps2 must be > 0, got {self.gravity_mps2}")
        if not self.camera_wobble_period_s > 0:
            raise ValueError(
                f"camera_wobble_period_s must be > 0, got {self.camera_wobble_period_s}")
        for i, leg in enumerate(self.legs):
            if len(leg) != 2 or not leg[0] >= 0 or not math.isfinite(leg[1]):
                raise ValueError(
                    f"legs[{i}] must be (length_m >= 0, turn_deg finite), got {leg!r}")

    @property
    def duration_s(self) -> float:
        """Time at which the last leg ends, s (the aircraft flies straight on after it)."""
        return _segments(self).end_s


@dataclass(frozen=True)
class Trajectory:
    """Dense samples of the true body state.

    Attributes:
        t_s: (N,) sample times, s.
        position_m: (N, 3) body origin in world.
        quaternion_wxyz: (N, 4) world_R_body, w first. Continuous in time (no sign
            flips between samples), so w may be negative.
        velocity_mps: (N, 3) body velocity in world.
        accel_world_mps2: (N, 3) body acceleration in world (gravity not included).
        omega_body_radps: (N, 3) angular rate of body w.r.t. world, in body.
    """

    t_s: np.ndarray
    position_m: np.ndarray
    quaternion_wxyz: np.ndarray
    velocity_mps: np.ndarray
    accel_world_mps2: np.ndarray
    omega_body_radps: np.ndarray

    @property
    def rotation_world_body(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices world_R_body."""
        return quat_wxyz_to_rotation(self.quaternion_wxyz)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


class _Kind(IntEnum):
    STRAIGHT = 0
    RAMP_IN = 1
    ARC = 2
    RAMP_OUT = 3


@dataclass(frozen=True)
class _Segments:
    """The plan cut into pieces, each with its start state (arrays of length S)."""

    kind: np.ndarray        # (S,) _Kind
    t0_s: np.ndarray        # (S,) start time
    duration_s: np.ndarray  # (S,)
    heading0_rad: np.ndarray  # (S,) heading at start
    xy0_m: np.ndarray       # (S, 2) position at start
    rate_rad: np.ndarray    # (S,) signed peak heading rate (0 on straights)
    end_s: float


def _segment_heading(kind: np.ndarray, tau: np.ndarray, T: np.ndarray, rate: np.ndarray,
                     heading0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heading, heading rate and its derivative at local time ``tau`` (all arrays alike)."""
    heading = np.array(heading0, dtype=float, copy=True)
    hrate = np.zeros_like(heading)
    hacc = np.zeros_like(heading)
    arc = kind == _Kind.ARC
    heading[arc] += rate[arc] * tau[arc]
    hrate[arc] = rate[arc]
    for ramp_kind, sign in ((_Kind.RAMP_IN, -1.0), (_Kind.RAMP_OUT, 1.0)):
        m = kind == ramp_kind
        if not np.any(m):
            continue
        Tm, wm, tm = T[m], rate[m], tau[m]
        u = np.pi * tm / Tm
        # Raised cosine: rate rises 0 -> w (RAMP_IN) or falls w -> 0 (RAMP_OUT), with zero
        # slope at both ends so the roll rate (which follows d(rate)/dt) is continuous.
        hrate[m] = 0.5 * wm * (1.0 + sign * np.cos(u))
        hacc[m] = -sign * 0.5 * wm * (np.pi / Tm) * np.sin(u)
        heading[m] += 0.5 * wm * (tm + sign * (Tm / np.pi) * np.sin(u))
    return heading, hrate, hacc


def _segment_xy(kind: np.ndarray, tau: np.ndarray, T: np.ndarray, rate: np.ndarray,
                heading0: np.ndarray, xy0: np.ndarray, speed: float) -> np.ndarray:
    """World (x, y) at local time ``tau``; (M,) inputs, xy0 (M, 2) -> (M, 2)."""
    xy = np.array(xy0, dtype=float, copy=True)
    st = kind == _Kind.STRAIGHT
    xy[st, 0] += speed * tau[st] * np.cos(heading0[st])
    xy[st, 1] += speed * tau[st] * np.sin(heading0[st])
    arc = kind == _Kind.ARC
    if np.any(arc):
        h0, w = heading0[arc], rate[arc]
        h = h0 + w * tau[arc]
        r = speed / w  # signed radius; arcs only exist at the full turn rate, never tiny
        xy[arc, 0] += r * (np.sin(h) - np.sin(h0))
        xy[arc, 1] += r * (np.cos(h0) - np.cos(h))
    ramp = (kind == _Kind.RAMP_IN) | (kind == _Kind.RAMP_OUT)
    if np.any(ramp):
        tr = tau[ramp]
        # Nodes s = tr (x + 1) / 2 on [0, tr] for every query at once: (M, Q).
        s = 0.5 * tr[:, None] * (_GL_X[None, :] + 1.0)
        kk = np.broadcast_to(kind[ramp][:, None], s.shape)
        h, _, _ = _segment_heading(
            kk.ravel(), s.ravel(), np.broadcast_to(T[ramp][:, None], s.shape).ravel(),
            np.broadcast_to(rate[ramp][:, None], s.shape).ravel(),
            np.broadcast_to(heading0[ramp][:, None], s.shape).ravel())
        h = h.reshape(s.shape)
        half = 0.5 * tr * speed
        xy[ramp, 0] += half * (np.cos(h) @ _GL_W)
        xy[ramp, 1] += half * (np.sin(h) @ _GL_W)
    return xy


def _segments(plan: FlightPlan) -> _Segments:
    """Cut the plan into straight / ramp / arc pieces and chain their start states."""
    v = plan.speed_mps
    w_max = math.radians(plan.turn_rate_dps)
    T_ramp = plan.bank_ramp_s
    pieces: list[tuple[_Kind, float, float]] = []  # (kind, duration, signed rate)
    for i, (length_m, turn_deg) in enumerate(plan.legs):
        # Keep a (possibly empty) first straight: it is what t < 0 extends backwards.
        if length_m > 0 or i == 0:
            pieces.append((_Kind.STRAIGHT, length_m / v, 0.0))
        angle = math.radians(turn_deg)
        if angle == 0.0:
            continue
        sign = math.copysign(1.0, angle)
        if T_ramp == 0.0:
            pieces.append((_Kind.ARC, abs(angle) / w_max, sign * w_max))
            continue
        # Each ramp turns by w_peak * T_ramp / 2; the arc covers the rest.
        w_peak = min(w_max, abs(angle) / T_ramp)
        t_arc = abs(angle) / w_peak - T_ramp
        pieces.append((_Kind.RAMP_IN, T_ramp, sign * w_peak))
        if t_arc > 0:
            pieces.append((_Kind.ARC, t_arc, sign * w_peak))
        pieces.append((_Kind.RAMP_OUT, T_ramp, sign * w_peak))
    if not pieces:
        pieces.append((_Kind.STRAIGHT, 0.0, 0.0))
    # The final, unbounded straight after the last leg.
    pieces.append((_Kind.STRAIGHT, math.inf, 0.0))

    S = len(pieces)
    kind = np.array([p[0] for p in pieces], dtype=int)
    dur = np.array([p[1] for p in pieces])
    rate = np.array([p[2] for p in pieces])
    t0 = np.zeros(S)
    h0 = np.zeros(S)
    xy0 = np.zeros((S, 2))
    h0[0] = math.radians(plan.heading_deg)
    xy0[0] = plan.start_xy_m
    for k in range(S - 1):
        one = np.array([dur[k]])
        args = (kind[k:k + 1], one, dur[k:k + 1], rate[k:k + 1])
        h_end, _, _ = _segment_heading(*args, h0[k:k + 1])
        xy_end = _segment_xy(*args, h0[k:k + 1], xy0[k:k + 1], v)
        t0[k + 1] = t0[k] + dur[k]
        h0[k + 1] = h_end[0]
        xy0[k + 1] = xy_end[0]
    return _Segments(kind, t0, dur, h0, xy0, rate, end_s=float(t0[-1]))


def _quat_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Quaternion (w first) of Rz(yaw) Ry(pitch) Rx(roll); continuous in the angles."""
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    return np.stack([cy * cp * cr + sy * sp * sr,
                     cy * cp * sr - sy * sp * cr,
                     cy * sp * cr + sy * cp * sr,
                     sy * cp * cr - cy * sp * sr], axis=-1)


def evaluate(plan: FlightPlan, t_s: np.ndarray) -> Trajectory:
    """The true body state at arbitrary times, analytically.

    Args:
        plan: the flight plan.
        t_s: (N,) times, s; any order, any value (outside the plan the aircraft flies
            straight, see the module docstring).

    Returns:
        The trajectory sampled at ``t_s``.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    if t.ndim != 1:
        raise ValueError(f"t_s must be 1-D, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t_s must be finite")
    seg = _segments(plan)
    v, g = plan.speed_mps, plan.gravity_mps2

    # Zero-length pieces share a start time with the next one; side="right" picks the
    # later piece, which is the one that actually covers t.
    k = np.clip(np.searchsorted(seg.t0_s, t, side="right") - 1, 0, None)
    kind, T, rate, h0 = seg.kind[k], seg.duration_s[k], seg.rate_rad[k], seg.heading0_rad[k]
    tau = t - seg.t0_s[k]
    heading, hrate, hacc = _segment_heading(kind, tau, T, rate, h0)
    xy = _segment_xy(kind, tau, T, rate, h0, seg.xy0_m[k], v)

    N = t.shape[0]
    position = np.column_stack([xy, np.full(N, plan.altitude_m)])
    ch, sh = np.cos(heading), np.sin(heading)
    velocity = np.column_stack([v * ch, v * sh, np.zeros(N)])
    accel = np.column_stack([-v * hrate * sh, v * hrate * ch, np.zeros(N)])

    # Coordinated turn: the specific force (a + g e_z) must lie in the body x-z plane.
    # With body y to the left, a left turn (hrate > 0) needs the left wing down, which
    # is a negative rotation about body x.
    c = v / g
    roll = -np.arctan(c * hrate)
    roll_rate = -c * hacc / (1.0 + (c * hrate) ** 2)
    pitch = np.zeros(N)
    pitch_rate = np.zeros(N)
    amp = math.radians(plan.camera_wobble_deg)
    if amp != 0.0:
        wr = 2.0 * np.pi / plan.camera_wobble_period_s
        wp = wr / math.sqrt(2.0)
        roll = roll + amp * np.sin(wr * t)
        roll_rate = roll_rate + amp * wr * np.cos(wr * t)
        pitch = amp * np.sin(wp * t)
        pitch_rate = amp * wp * np.cos(wp * t)

    # Body angular rate of R = Rz(yaw) Ry(pitch) Rx(roll): ZYX Euler-rate kinematics.
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    omega_body = np.column_stack([
        roll_rate - hrate * sp,
        cr * pitch_rate + sr * cp * hrate,
        -sr * pitch_rate + cr * cp * hrate,
    ])
    return Trajectory(
        t_s=t,
        position_m=position,
        quaternion_wxyz=_quat_zyx(heading, pitch, roll),
        velocity_mps=velocity,
        accel_world_mps2=accel,
        omega_body_radps=omega_body,
    )


def plan_trajectory(plan: FlightPlan, duration_s: float, rate_hz: float) -> Trajectory:
    """The true body state sampled uniformly from t = 0.

    Args:
        plan: the flight plan.
        duration_s: last sample time, s (included when it falls on the grid).
        rate_hz: sampling rate, Hz.

    Returns:
        ``evaluate(plan, k / rate_hz)`` for k = 0 .. floor(duration_s * rate_hz).
    """
    if not duration_s >= 0:
        raise ValueError(f"duration_s must be >= 0, got {duration_s}")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    # The small slack keeps the end sample when duration * rate is an integer up to
    # floating-point error (e.g. 0.3 s at 10 Hz).
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    return evaluate(plan, np.arange(n) / rate_hz)
