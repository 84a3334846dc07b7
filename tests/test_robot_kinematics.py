"""Raven II kinematics: the modified-DH table, FK/IK round trips, unreachable poses."""
import math

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.robot.raven2_kinematics import (A12, A23, ARMS, D4, JOINT_HOME, JOINT_LOWER, JOINT_UPPER,
                                                        LW, Raven2Kinematics)


def _dh(alpha, a, theta, d):
    """Craig's modified DH link transform RotX(alpha) TransX(a) RotZ(theta) TransZ(d), as matrices."""
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1.0]])
    tx = np.eye(4)
    tx[0, 3] = a
    rz = np.array([[ct, -st, 0, 0], [st, ct, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    tz = np.eye(4)
    tz[2, 3] = d
    return rx @ tx @ rz @ tz


def _fk_reference(arm, q):
    """The DH table of SPEC 4 / the Raven II source, multiplied out link by link."""
    a = ARMS[arm]
    th = [q[0] + a.offset[0], q[1] + a.offset[1], a.theta3, q[3] + a.offset[3], q[4] + a.offset[4], q[5] + a.offset[5]]
    ds = [0, 0, q[2], D4, 0, 0]
    aa = [0, 0, 0, 0, 0, LW]
    T = np.eye(4)
    for i in range(6):
        T = T @ _dh(a.alpha[i], aa[i], th[i], ds[i])
    return T


def _random_q(rng, n):
    return rng.uniform(JOINT_LOWER, JOINT_UPPER, size=(n, 6))


@pytest.mark.parametrize("arm", ["right", "left"])
def test_fk_matches_the_dh_table(arm):
    kin = Raven2Kinematics(arm)
    assert ARMS[arm].alpha[1] == A12
    assert ARMS[arm].alpha[2] in (A23, math.pi - A23)
    for q in _random_q(np.random.default_rng(1), 200):
        np.testing.assert_allclose(kin.fk(q), _fk_reference(arm, q), atol=1e-12)


def test_geometry_of_the_spherical_mechanism():
    kin = Raven2Kinematics("right")
    for q in _random_q(np.random.default_rng(2), 100):
        T = kin.fk(q)
        (wx, wy, wz), u = kin.wrist_point(q)
        wrist = np.array([wx, wy, wz])
        # the wrist is |d3 + d4| from the remote centre of motion, the tip Lw from the wrist
        assert np.linalg.norm(wrist) == pytest.approx(abs(q[2] + D4), abs=1e-12)
        assert np.linalg.norm(T[:3, 3] - wrist) == pytest.approx(LW, abs=1e-12)
        # the angle between the shoulder axis and the shaft depends on the elbow only (75 / 52 deg links)
        z1, z2 = kin.joint_axes(q)
        assert abs(np.dot(z1, z2)) == pytest.approx(math.cos(A12), abs=1e-12)
        assert abs(np.dot(z2, u)) == pytest.approx(math.cos(A23), abs=1e-12)


def test_left_arm_mirrors_the_right_arm():
    """Same joint values, mirror images across the base x-z plane: the wrist point always, the
    tip when the tool is straight (the tool joints rotate the other way on a mirrored arm)."""
    right, left = Raven2Kinematics("right"), Raven2Kinematics("left")
    for q in _random_q(np.random.default_rng(3), 50):
        np.testing.assert_allclose(left.wrist_point(q)[0], np.multiply(right.wrist_point(q)[0], [1, -1, 1]),
                                   atol=1e-12)
        q[3:] = 0.0
        np.testing.assert_allclose(left.fk(q)[:3, 3], right.fk(q)[:3, 3] * [1, -1, 1], atol=1e-12)


@pytest.mark.parametrize("arm", ["right", "left"])
def test_ik_of_fk_returns_the_joints(arm):
    kin = Raven2Kinematics(arm)
    rng = np.random.default_rng(4)
    for q in _random_q(rng, 1000):
        T = kin.fk(q)
        # a seed near q (as a previous tick's setpoint would be) picks q out of the up to 8 solutions
        seed = np.clip(q + rng.normal(0, 0.02, 6) * [1, 1, 0.1, 1, 1, 1], JOINT_LOWER, JOINT_UPPER)
        np.testing.assert_allclose(kin.ik(T, seed), q, atol=1e-9)
        # every closed-form candidate reproduces the pose
        cands = kin.ik_candidates(T)
        assert 1 <= len(cands) <= 8
        for c in cands:
            np.testing.assert_allclose(kin.fk(c), T, atol=1e-9)


def test_fk_of_ik_reaches_random_points():
    """Random positions around the home tip, with the home orientation: every reachable one is
    reached exactly; unreachable ones raise InputError (and most of the box is reachable)."""
    kin = Raven2Kinematics("right")
    T0 = kin.fk(JOINT_HOME)
    rng = np.random.default_rng(5)
    reached = 0
    for dp in rng.uniform(-0.03, 0.03, size=(1000, 3)):
        T = T0.copy()
        T[:3, 3] += dp
        try:
            q = kin.ik(T, JOINT_HOME)
        except InputError as e:
            assert "out of reach" in str(e)
            continue
        reached += 1
        assert np.all(q >= JOINT_LOWER - 1e-12) and np.all(q <= JOINT_UPPER + 1e-12)
        np.testing.assert_allclose(kin.fk(q), T, atol=1e-9)
    assert reached > 900


def test_unreachable_poses_raise_and_name_the_limit():
    kin = Raven2Kinematics("right")
    T = kin.fk(JOINT_HOME)
    far = T.copy()
    far[:3, 3] *= 10.0          # 0.8 m from the RCM: insertion limit
    with pytest.raises(InputError, match="insertion"):
        kin.ik(far, JOINT_HOME)
    at_rcm = T.copy()
    at_rcm[:3, 3] = 0.0         # the tip at the remote centre of motion: degenerate
    with pytest.raises(InputError, match="out of reach"):
        kin.ik(at_rcm, JOINT_HOME)
