"""Tests of the analytic flight path: kinematic consistency, geometry, continuity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from cdtm_graph.geometry import quat_wxyz_to_rotation, so3_log
from cdtm_graph.sim.trajectory import FlightPlan, Trajectory, evaluate, plan_trajectory

G_MPS2 = 9.80665

# Central differences with step H_S: truncation ~ jerk * H_S^2 / 6 ~ 1e-8 and round-off
# ~ 1e4 m * 1e-16 / H_S ~ 1e-8, so these tolerances sit two decades above both.
H_S = 1e-4
FD_VEL_TOL_MPS = 1e-6
FD_ACC_TOL_MPS2 = 1e-6
FD_OMEGA_TOL_RADPS = 1e-7
# Adaptive quadrature of the analytic velocity (epsabs 1e-10 per piece) vs positions.
QUAD_POS_TOL_M = 1e-6
# Exact identities evaluated in floating point on ~1e4 m coordinates.
EXACT_TOL = 1e-9

WOBBLY = FlightPlan(camera_wobble_deg=2.0, camera_wobble_period_s=7.0)


def _segment_boundaries(plan: FlightPlan) -> np.ndarray:
    """Start times of straights, ramps and arcs, rebuilt from the plan by hand."""
    v, w = plan.speed_mps, math.radians(plan.turn_rate_dps)
    out, t = [], 0.0
    for length_m, turn_deg in plan.legs:
        t += length_m / v
        out.append(t)
        if turn_deg:
            a = math.radians(abs(turn_deg))
            w_peak = min(w, a / plan.bank_ramp_s)
            out += [t + plan.bank_ramp_s, t + a / w_peak]
            t += a / w_peak + plan.bank_ramp_s
            out.append(t)
    return np.array(out)


def _all_times(plan: FlightPlan) -> np.ndarray:
    """Times covering every segment kind, before, inside and after the plan."""
    return np.linspace(-5.0, plan.duration_s + 5.0, 3001)


def test_duration_matches_legs_and_turns():
    plan = FlightPlan()
    # Each turn of angle A lasts A / rate + one ramp (the two cosine ramps together turn
    # by rate * ramp and last 2 ramps).
    expected = 6000.0 / 200.0 + 2 * (30.0 + 2.0)
    assert plan.duration_s == pytest.approx(expected, abs=EXACT_TOL)


@pytest.mark.parametrize("plan", [FlightPlan(), WOBBLY], ids=["level", "wobble"])
def test_derivatives_match_central_differences(plan):
    t = _all_times(plan)
    mid, up, down = evaluate(plan, t), evaluate(plan, t + H_S), evaluate(plan, t - H_S)
    vel_fd = (up.position_m - down.position_m) / (2 * H_S)
    acc_fd = (up.velocity_mps - down.velocity_mps) / (2 * H_S)
    R_up, R_down = up.rotation_world_body, down.rotation_world_body
    omega_fd = so3_log(np.swapaxes(R_down, 1, 2) @ R_up) / (2 * H_S)
    np.testing.assert_allclose(mid.velocity_mps, vel_fd, atol=FD_VEL_TOL_MPS)
    np.testing.assert_allclose(mid.accel_world_mps2, acc_fd, atol=FD_ACC_TOL_MPS2)
    np.testing.assert_allclose(mid.omega_body_radps, omega_fd, atol=FD_OMEGA_TOL_RADPS)
    # The test exercises real motion, not a constant state.
    assert np.abs(mid.omega_body_radps[:, 0]).max() > 0.3
    assert np.abs(mid.accel_world_mps2).max() > 10.0


def test_position_is_the_integral_of_velocity_across_all_segments():
    """Catches errors in the ramp quadrature and in chaining segment start states."""
    plan = WOBBLY
    knots = np.concatenate([[0.0], _segment_boundaries(plan), [plan.duration_s + 3.0]])
    knots = np.unique(knots)
    p = evaluate(plan, knots).position_m
    for axis in (0, 1):
        def vel(s, axis=axis):
            return evaluate(plan, np.array([s])).velocity_mps[0, axis]
        steps = [quad(vel, a, b, epsabs=1e-10, epsrel=1e-13)[0]
                 for a, b in zip(knots[:-1], knots[1:], strict=True)]
        integral = p[0, axis] + np.concatenate([[0.0], np.cumsum(steps)])
        np.testing.assert_allclose(p[:, axis], integral, atol=QUAD_POS_TOL_M)


def test_state_is_continuous_at_segment_boundaries():
    plan = WOBBLY
    tb = _segment_boundaries(plan)
    eps = 1e-9
    before, after = evaluate(plan, tb - eps), evaluate(plan, tb + eps)
    for name, tol in [("position_m", 1e-5), ("velocity_mps", 1e-6),
                      ("accel_world_mps2", 1e-6), ("omega_body_radps", 1e-6),
                      ("quaternion_wxyz", 1e-8)]:
        np.testing.assert_allclose(getattr(before, name), getattr(after, name), atol=tol,
                                   err_msg=name)


def test_instant_bank_onset_makes_the_rate_jump():
    """bank_ramp_s = 0 is allowed; the documented price is a jump in the body rate."""
    plan = FlightPlan(bank_ramp_s=0.0)
    t_turn = 2000.0 / plan.speed_mps
    jump = evaluate(plan, np.array([t_turn + 1e-9])).omega_body_radps[0] - \
        evaluate(plan, np.array([t_turn - 1e-9])).omega_body_radps[0]
    assert np.linalg.norm(jump) > 0.01


def test_pure_arc_ends_where_geometry_says():
    """A 90 deg left turn from heading 0 at origin, without ramps: centre at (0, r)."""
    plan = FlightPlan(legs=((0.0, 90.0),), bank_ramp_s=0.0, start_xy_m=(10.0, -20.0))
    r = plan.speed_mps / math.radians(plan.turn_rate_dps)
    end = evaluate(plan, np.array([plan.duration_s]))
    np.testing.assert_allclose(end.position_m[0], [10.0 + r, -20.0 + r, 1000.0],
                               atol=EXACT_TOL * r)
    np.testing.assert_allclose(end.velocity_mps[0], [0.0, plan.speed_mps, 0.0], atol=1e-9)


@pytest.mark.parametrize("turns_deg", [(90.0, -90.0, 0.0), (270.0, 4.0, -1.0)])
def test_final_heading_is_initial_plus_turns(turns_deg):
    """Also covers a turn too small to reach the full rate within its ramps (4 and -1 deg)."""
    plan = FlightPlan(heading_deg=30.0, legs=tuple((500.0, a) for a in turns_deg))
    v = evaluate(plan, np.array([plan.duration_s + 1.0])).velocity_mps[0]
    heading = math.radians(30.0 + sum(turns_deg))
    np.testing.assert_allclose(v, plan.speed_mps * np.array(
        [math.cos(heading), math.sin(heading), 0.0]), atol=1e-9)


def test_level_constant_speed_coordinated_and_nose_along_velocity():
    plan = FlightPlan()
    traj = evaluate(plan, _all_times(plan))
    R = traj.rotation_world_body
    np.testing.assert_allclose(traj.position_m[:, 2], plan.altitude_m, atol=EXACT_TOL)
    np.testing.assert_allclose(np.linalg.norm(traj.velocity_mps, axis=1), plan.speed_mps,
                               rtol=1e-12)
    # Without wobble the nose (body x) points along the velocity.
    np.testing.assert_allclose(R[:, :, 0], traj.velocity_mps / plan.speed_mps, atol=1e-12)
    # Coordinated: the specific force has no component along the wings (body y).
    f_body = np.einsum("nji,nj->ni", R, traj.accel_world_mps2 + [0.0, 0.0, G_MPS2])
    np.testing.assert_allclose(f_body[:, 1], 0.0, atol=1e-12)


def test_left_turn_banks_left_wing_down_by_coordinated_angle():
    plan = FlightPlan()
    t_mid_arc = 2000.0 / plan.speed_mps + 15.0  # inside the first (left, +90 deg) turn
    R = evaluate(plan, np.array([t_mid_arc])).rotation_world_body[0]
    w = math.radians(plan.turn_rate_dps)
    bank = math.atan(plan.speed_mps * w / G_MPS2)
    assert R[2, 1] == pytest.approx(-math.sin(bank), abs=1e-12)  # body y (left) points down
    assert R[2, 2] == pytest.approx(math.cos(bank), abs=1e-12)


def test_quaternion_is_continuous_unit_and_starts_level():
    plan = FlightPlan(legs=((500.0, 270.0), (500.0, 200.0)), camera_wobble_deg=1.0)
    traj = plan_trajectory(plan, plan.duration_s, 20.0)
    q = traj.quaternion_wxyz
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    # No sign flips between neighbours although the heading passes +-180 deg.
    assert np.min(np.sum(q[1:] * q[:-1], axis=1)) > 0.99
    np.testing.assert_allclose(q[0], [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(quat_wxyz_to_rotation(q), traj.rotation_world_body)


def test_before_start_and_after_end_fly_straight():
    plan = FlightPlan(legs=((0.0, 45.0),))  # a turn right at t = 0
    traj = evaluate(plan, np.array([-2.0, 0.0, plan.duration_s, plan.duration_s + 2.0]))
    np.testing.assert_allclose(traj.position_m[0], [-2.0 * plan.speed_mps, 0.0, 1000.0])
    np.testing.assert_allclose(traj.accel_world_mps2[[0, 3]], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.position_m[3] - traj.position_m[2],
                               2.0 * traj.velocity_mps[2], atol=EXACT_TOL)


def test_plan_trajectory_samples_uniformly_including_the_end():
    traj = plan_trajectory(FlightPlan(), 0.3, 10.0)
    assert isinstance(traj, Trajectory)
    assert len(traj) == 4
    np.testing.assert_allclose(traj.t_s, [0.0, 0.1, 0.2, 0.3])
    for name in ("position_m", "velocity_mps", "accel_world_mps2", "omega_body_radps"):
        assert getattr(traj, name).shape == (4, 3)
    assert traj.quaternion_wxyz.shape == (4, 4)


@pytest.mark.parametrize("kwargs", [
    {"speed_mps": 0.0}, {"turn_rate_dps": -1.0}, {"bank_ramp_s": -0.1},
    {"legs": ((-5.0, 0.0),)}, {"legs": ((5.0, math.nan),)}, {"camera_wobble_period_s": 0.0},
])
def test_invalid_plan_raises(kwargs):
    with pytest.raises(ValueError):
        FlightPlan(**kwargs)


def test_invalid_times_raise():
    with pytest.raises(ValueError):
        evaluate(FlightPlan(), np.array([0.0, math.nan]))
    with pytest.raises(ValueError):
        plan_trajectory(FlightPlan(), 1.0, 0.0)
