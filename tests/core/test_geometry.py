"""Rotation helpers: property-based round trips (hypothesis), checked against GTSAM."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdtm_graph.geometry import (
    largest_eigenvalue_sym3,
    make_pose,
    quat_wxyz_to_rotation,
    rays_in_world,
    rotation_to_quat_wxyz,
    so3_exp,
    so3_log,
    sym3_eigenvalue_range,
)

#: Round trips in double precision.
ROUND_TRIP_TOL = 1e-9

rotation_vectors = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3).map(
    np.array).filter(lambda w: np.linalg.norm(w) < np.pi - 1e-3)


@settings(max_examples=300, deadline=None)
@given(rotation_vectors)
def test_exp_log_round_trip_and_agree_with_gtsam(w):
    R = so3_exp(w)
    np.testing.assert_allclose(R, gtsam.Rot3.Expmap(w).matrix(), atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(so3_log(R), w, atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=ROUND_TRIP_TOL)


@settings(max_examples=300, deadline=None)
@given(rotation_vectors)
def test_quaternion_round_trip_w_first(w):
    R = so3_exp(w)
    q = rotation_to_quat_wxyz(R)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < ROUND_TRIP_TOL
    np.testing.assert_allclose(quat_wxyz_to_rotation(q), R, atol=ROUND_TRIP_TOL)


@settings(max_examples=300, deadline=None)
@given(rotation_vectors)
def test_quaternions_are_hamilton_as_gtsam(w):
    """Signed components against GTSAM's Hamilton quaternions (docs/flightlog.md), both ways.

    JPL quaternions (the transposed matrix) differ in the sign of x, y, z, which a
    comparison of absolute values cannot see. q and -q are one rotation: GTSAM's sign
    is matched to ours (w >= 0) before comparing.
    """
    R = so3_exp(w)
    g = gtsam.Rot3(R).toQuaternion()
    q_gtsam = np.array([g.w(), g.x(), g.y(), g.z()])
    q = rotation_to_quat_wxyz(R)
    np.testing.assert_allclose(q, np.copysign(1.0, q @ q_gtsam) * q_gtsam, atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(quat_wxyz_to_rotation(q_gtsam),
                               gtsam.Rot3.Quaternion(*q_gtsam).matrix(), atol=ROUND_TRIP_TOL)


def test_quarter_turn_about_z_maps_x_to_y():
    """By hand: q = (cos 45deg, 0, 0, sin 45deg) turns +90 deg about z, so a body x axis
    points along world y (ENU: east -> north), the matrix [[0, -1, 0], [1, 0, 0], [0, 0, 1]]."""
    half = np.sqrt(0.5)
    q = np.array([half, 0.0, 0.0, half])
    R_expected = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R = quat_wxyz_to_rotation(q)
    np.testing.assert_allclose(R, R_expected, atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(rotation_to_quat_wxyz(R_expected), q, atol=ROUND_TRIP_TOL)


@settings(max_examples=100, deadline=None)
@given(st.floats(1e-12, 1e-6))
def test_log_is_accurate_for_tiny_angles(angle):
    w = np.array([angle, -0.5 * angle, 0.25 * angle])
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, rtol=1e-6)


def test_rays_in_world_are_each_cameras_rotation_and_centre(rng):
    cams = np.stack([make_pose(so3_exp(rng.normal(size=3)), rng.normal(0, 100, 3))
                     for _ in range(5)])
    camera = rng.integers(0, 5, 40)
    ray_cam = rng.normal(size=(40, 3))
    centre, ray = rays_in_world(cams, camera, ray_cam)
    for m in range(40):
        np.testing.assert_array_equal(centre[m], cams[camera[m], :3, 3])
        np.testing.assert_allclose(ray[m], cams[camera[m], :3, :3] @ ray_cam[m], rtol=1e-14,
                                   atol=1e-14)


def test_the_closed_form_eigenvalues_of_a_symmetric_3x3_are_lapacks(rng):
    """Smallest and largest eigenvalue against ``eigvalsh`` over six decades of scale,
    with a singular matrix, a multiple of the identity and a non-contiguous block."""
    for _ in range(500):
        L = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-3, 3)
        for A in (L @ L.T, L[:, :2] @ L[:, :2].T):
            w = np.linalg.eigvalsh(A)
            smallest, largest = sym3_eigenvalue_range(A)
            assert largest == pytest.approx(w[-1], rel=1e-12)
            assert abs(smallest - w[0]) <= 1e-12 * w[-1]
    assert sym3_eigenvalue_range(2.5 * np.eye(3)) == (2.5, 2.5)
    cov = np.diag([1.0, 2.0, 3.0, 9.0, 4.0, 1.0])
    assert largest_eigenvalue_sym3(cov[3:, 3:]) == pytest.approx(9.0, rel=1e-14)


def test_a_covariance_block_compiles_the_eigenvalue_kernel_no_second_time():
    """A pose covariance's 3x3 block (a strided view) reaches the kernel as the
    contiguous array it is compiled for: one signature, one compilation on a first run
    (issue 22). Catches: the boundary's cast dropped (``np.asarray``: an 'A'-layout
    signature compiled beside the 'C' one)."""
    largest_eigenvalue_sym3(np.eye(3))  # the contiguous signature, as the package calls it
    compiled = set(sym3_eigenvalue_range.signatures)
    cov = np.diag(np.arange(1.0, 7.0))
    assert largest_eigenvalue_sym3(cov[3:, 3:]) == pytest.approx(6.0, rel=1e-14)
    assert set(sym3_eigenvalue_range.signatures) == compiled
