"""Raven II kinematics: modified-DH forward kinematics and closed-form inverse kinematics.

Convention (Craig's *modified* DH, as in the Raven II control software, ``r2_kinematics.cpp``,
and King, Nia Kosari, Hannaford & Ma, "Kinematic analysis of the Raven-II research surgical
robot platform", UW EE tech. report 2012-0006; Hannaford et al., "Raven-II: an open platform for
surgical robotics research", IEEE TBME 2013)::

    T_{i-1,i} = RotX(alpha_{i-1}) * TransX(a_{i-1}) * RotZ(theta_i) * TransZ(d_i)

=====  =============  ===========  =========================  ===========
 i      alpha_{i-1}    a_{i-1}      theta_i                    d_i
=====  =============  ===========  =========================  ===========
 1      pi (R) / 0 (L) 0           th1 (shoulder)             0
 2      A12 = 75 deg   0           th2 (elbow)                0
 3      A23 = 52 deg (R) / pi - A23 (L)   0   -pi/2 (R) / +pi/2 (L)   d3 (insertion)
 4      0              0           th4 (tool roll)            d4 = -0.47 m
 5      pi/2           0           th5 (wrist)                0
 6      pi/2           Lw = 0.013  th6 (grasper yaw)          0
=====  =============  ===========  =========================  ===========

Frame 0 sits at the remote centre of motion (RCM): the shoulder (z1) and elbow (z2) axes and
the tool shaft (z3 = z4) all pass through it, and the shaft's distance to the wrist is |d3 + d4|.
Frame 6's origin is the tool tip (the jaw pivot is Lw before it along x5).

Joint vector (the Raven's own joint space, in which the limits are stated; SI units):
``q = [shoulder, elbow, insertion, tool_roll, wrist, grasper_yaw]`` with
``th1 = q0 + off1, th2 = q1 + off2, d3 = q2, th4 = q3, th5 = q4 - pi/2, th6 = q5`` and
(off1, off2) = (25 deg, 0) for the right (green) arm, (205 deg, 180 deg) for the left (gold) one.
Joint limits (``defines.h``, RAVEN_II_RELEASE_02; identical for both arms): shoulder 0..90 deg,
elbow 45..135 deg, insertion 0.23..0.56 m, tool roll +/-182 deg, wrist +/-75 deg; the grasper
yaw (mean of the two jaw angles, each limited to +/-89 deg) is limited here to +/-80 deg.

Inverse kinematics (closed form; up to 8 candidates, the one within the limits nearest a seed):
1. wrist point: x5 is perpendicular to z6 and lies in the plane of the shaft, which contains the
   RCM, so x5 = +/- the normalised projection of (RCM - tip) onto the x6-y6 plane, and
   p5 = p6 - Lw x5 (two candidates);
2. insertion: d3 + d4 = -|p5| (wrist beyond the RCM) or +|p5| (two candidates);
3. elbow from the z component of the shaft direction u = p5 / (d3 + d4):
   cos th2 = (cos A12 cos A23' - v_z) / (sin A12 sin A23'), v = RotX(alpha0)^T u (two candidates);
4. shoulder from the x-y components of v: th1 = atan2(v_y, v_x) - atan2(m_y, m_x);
5. wrist joints from R36 = R03^T R06: th5 = atan2(x5_z, -R36[2,2]) (x5 in frame 3),
   th4 from (c5 x5 + s5 z6) projected on x3-y3, th6 from R56 = R05^T R06.
Angles are unwrapped to the copy nearest the seed (the roll range exceeds 360 deg).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pointfence.kernels.errors import InputError

A12 = math.radians(75.0)
A23 = math.radians(52.0)
D4 = -0.47
LW = 0.013

JOINT_NAMES = ("shoulder", "elbow", "insertion", "tool_roll", "wrist", "grasper_yaw")
DEG = math.pi / 180.0
#: Raven II joint limits (defines.h, RAVEN_II_RELEASE_02); grasper yaw: see module docstring
JOINT_LOWER = np.array([0.0 * DEG, 45.0 * DEG, 0.23, -182.0 * DEG, -75.0 * DEG, -80.0 * DEG])
JOINT_UPPER = np.array([90.0 * DEG, 135.0 * DEG, 0.56, 182.0 * DEG, 75.0 * DEG, 80.0 * DEG])
#: the Raven's home pose (defines.h: shoulder 30 deg, elbow 90 deg, insertion 0.4 m)
JOINT_HOME = np.array([30.0 * DEG, 90.0 * DEG, 0.40, 0.0, 0.0, 0.0])
#: weight of the insertion (m) against angles (rad) when choosing the IK solution nearest a seed
INSERTION_WEIGHT = 100.0
_EPS = 1e-9


@dataclass(frozen=True)
class Raven2Arm:
    """DH table of one arm: alpha_{i-1}, fixed theta3, joint-to-theta offsets."""

    name: str
    alpha: tuple           # alpha_0 .. alpha_5
    theta3: float          # fixed theta of the prismatic joint 3
    offset: tuple          # theta_i = q_i + offset_i (i = 0..5; offset[2] is for d3 and is 0)


RIGHT = Raven2Arm("right", (math.pi, A12, A23, 0.0, math.pi / 2, math.pi / 2), -math.pi / 2,
                  (25.0 * DEG, 0.0, 0.0, 0.0, -90.0 * DEG, 0.0))
LEFT = Raven2Arm("left", (0.0, A12, math.pi - A23, 0.0, math.pi / 2, math.pi / 2), math.pi / 2,
                 (205.0 * DEG, 180.0 * DEG, 0.0, 0.0, -90.0 * DEG, 0.0))
ARMS = {"right": RIGHT, "left": LEFT}


def _wrap_near(angle: float, ref: float) -> float:
    """``angle`` + 2 pi k nearest ``ref``."""
    return angle + 2.0 * math.pi * round((ref - angle) / (2.0 * math.pi))


class Raven2Kinematics:
    """Forward and inverse kinematics of one Raven II arm (scalar math: cheap per call)."""

    def __init__(self, arm: str = "right", lower=JOINT_LOWER, upper=JOINT_UPPER):
        if arm not in ARMS:
            raise InputError(f"arm = {arm!r}; expected 'right' or 'left'")
        self.arm = ARMS[arm]
        self.lower = np.asarray(lower, dtype=float).copy()
        self.upper = np.asarray(upper, dtype=float).copy()
        self._lo, self._hi = self.lower.tolist(), self.upper.tolist()
        self._sign_first = 1.0
        al = self.arm.alpha
        self._ca = tuple(math.cos(a) for a in al)
        self._sa = tuple(math.sin(a) for a in al)
        # fixed rotation of joint 3 (theta3), and the frame-3 direction of the shaft in frame 2
        self._c3, self._s3 = math.cos(self.arm.theta3), math.sin(self.arm.theta3)

    # ------------------------------------------------------------------ forward kinematics
    def thetas(self, q) -> tuple:
        o = self.arm.offset
        return (q[0] + o[0], q[1] + o[1], q[2], q[3] + o[3], q[4] + o[4], q[5] + o[5])

    def fk_into(self, q, out: np.ndarray) -> np.ndarray:
        """Tool-tip pose (base frame) at joints ``q`` written into the 4x4 ``out``."""
        th1, th2, d3, th4, th5, th6 = self.thetas(q)
        ca, sa = self._ca, self._sa
        # running rotation as columns c0, c1, c2 (each a 3-tuple) and position p
        x0, x1, x2 = 1.0, 0.0, 0.0
        y0, y1, y2 = 0.0, 1.0, 0.0
        z0, z1, z2 = 0.0, 0.0, 1.0
        px = py = pz = 0.0
        thetas = (th1, th2, self.arm.theta3, th4, th5, th6)
        ds = (0.0, 0.0, d3, D4, 0.0, 0.0)
        a_prev = (0.0, 0.0, 0.0, 0.0, 0.0, LW)
        for i in range(6):
            c, s = ca[i], sa[i]
            # RotX(alpha): c1' = c c1 + s c2, c2' = -s c1 + c c2
            if s != 0.0 or c != 1.0:
                y0, y1, y2, z0, z1, z2 = (c * y0 + s * z0, c * y1 + s * z1, c * y2 + s * z2,
                                          -s * y0 + c * z0, -s * y1 + c * z1, -s * y2 + c * z2)
            a = a_prev[i]
            if a != 0.0:
                px += a * x0
                py += a * x1
                pz += a * x2
            ct, st = math.cos(thetas[i]), math.sin(thetas[i])
            x0, x1, x2, y0, y1, y2 = (ct * x0 + st * y0, ct * x1 + st * y1, ct * x2 + st * y2,
                                      -st * x0 + ct * y0, -st * x1 + ct * y1, -st * x2 + ct * y2)
            d = ds[i]
            if d != 0.0:
                px += d * z0
                py += d * z1
                pz += d * z2
        out[0, 0], out[0, 1], out[0, 2], out[0, 3] = x0, y0, z0, px
        out[1, 0], out[1, 1], out[1, 2], out[1, 3] = x1, y1, z1, py
        out[2, 0], out[2, 1], out[2, 2], out[2, 3] = x2, y2, z2, pz
        out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0
        return out

    def fk(self, q) -> np.ndarray:
        """Tool-tip pose (4x4, base frame) at joints ``q``."""
        return self.fk_into(q, np.empty((4, 4)))

    def wrist_point(self, q) -> tuple:
        """Position of the wrist (frame 4/5 origin) in the base frame, and the shaft unit vector
        z3 (pointing from the RCM along +z3; the wrist is at (d3 + d4) z3)."""
        th1, th2 = q[0] + self.arm.offset[0], q[1] + self.arm.offset[1]
        ux, uy, uz = self._shaft(th1, th2)
        L = q[2] + D4
        return (L * ux, L * uy, L * uz), (ux, uy, uz)

    def _shaft(self, th1: float, th2: float) -> tuple:
        """z3 in the base frame: RotX(a0) RotZ(th1) RotX(a1) RotZ(th2) RotX(a2) e_z."""
        ca, sa = self._ca, self._sa
        c2, s2 = math.cos(th2), math.sin(th2)
        # w = RotX(a2) e_z = (0, -s a2, c a2); RotZ(th2) w
        wx, wy, wz = s2 * sa[2], -c2 * sa[2], ca[2]
        # RotX(a1)
        mx, my, mz = wx, ca[1] * wy - sa[1] * wz, sa[1] * wy + ca[1] * wz
        c1, s1 = math.cos(th1), math.sin(th1)
        vx, vy, vz = c1 * mx - s1 * my, s1 * mx + c1 * my, mz
        # RotX(a0)
        return vx, ca[0] * vy - sa[0] * vz, sa[0] * vy + ca[0] * vz

    def joint_axes(self, q) -> tuple:
        """Base-frame unit axes of the shoulder (z1) and elbow (z2) joints; both pass the RCM."""
        ca, sa = self._ca, self._sa
        z1 = (0.0, -sa[0], ca[0])
        th1 = q[0] + self.arm.offset[0]
        c1, s1 = math.cos(th1), math.sin(th1)
        # RotX(a0) RotZ(th1) (0, -s a1, c a1)
        vx, vy, vz = s1 * sa[1], -c1 * sa[1], ca[1]
        z2 = (vx, ca[0] * vy - sa[0] * vz, sa[0] * vy + ca[0] * vz)
        return z1, z2

    # ------------------------------------------------------------------ inverse kinematics
    def ik_candidates(self, T) -> list:
        """Every closed-form solution (joint vectors, angles in (-pi, pi]) reaching base-frame pose
        ``T``, ignoring joint limits; empty when the pose is degenerate (tip at the RCM)."""
        return [np.array(q[:6]) for q, _ in self._candidates(_rows(T), None, None, None)]

    def ik(self, T, seed=None) -> np.ndarray:
        """Joints within the limits reaching base-frame pose ``T`` (4x4), nearest ``seed``
        (weighted: insertion x 100). Raises InputError naming the nearest violated limit."""
        seed_t = tuple(float(x) for x in (JOINT_HOME if seed is None else seed))
        lim = _Limits(self._lo, self._hi)
        rows = _rows(T)
        best = None
        bound = [math.inf]   # best cost so far; the generator skips candidates that cannot beat it
        for q, cost in self._candidates(rows, seed_t, lim, bound):
            if cost < bound[0]:
                best, bound[0] = q, cost
                self._sign_first = q[6]
        if best is None:
            where = "[" + ", ".join(f"{rows[i][3]:.6g}" for i in range(3)) + "]"
            if lim.msg is None:
                raise InputError(f"pose at {where} m (base frame) is out of reach: the tool cannot reach "
                                 f"that position with that orientation (too close to the RCM or beyond the "
                                 f"elbow's range)")
            raise InputError(f"pose at {where} m (base frame) is out of reach: {lim.msg}")
        lo, hi = self._lo, self._hi
        return np.array([lo[i] if best[i] < lo[i] else (hi[i] if best[i] > hi[i] else best[i]) for i in range(6)])

    def _candidates(self, T, seed, lim, bound):
        """Closed-form solutions for pose rows ``T`` (nested lists), as ([q0..q5, sign], cost).
        With ``lim``, those outside the limits are dropped as early as possible (the least
        violation is recorded in lim); with ``bound`` (a one-element list holding the best cost
        so far), those whose positioning joints alone already cost more are skipped before the
        wrist is solved. The x5 sign that won last time is tried first."""
        ca, sa = self._ca, self._sa
        off = self.arm.offset
        r00, r01, r02, px = T[0]
        r10, r11, r12, py = T[1]
        r20, r21, r22, pz = T[2]
        # tip -> RCM in frame 6: -R^T p; projection on x6-y6
        rx = -(r00 * px + r10 * py + r20 * pz)
        ry = -(r01 * px + r11 * py + r21 * pz)
        nrm = math.hypot(rx, ry)
        if nrm < _EPS:
            return
        nx6, ny6 = rx / nrm, ry / nrm
        # the same direction in the base frame
        nbx = r00 * nx6 + r01 * ny6
        nby = r10 * nx6 + r11 * ny6
        nbz = r20 * nx6 + r21 * ny6
        denom = sa[1] * sa[2]
        cc = ca[1] * ca[2]
        s0 = s1 = 0.0
        if seed is not None:
            s0, s1 = seed[0], seed[1]
        w2 = INSERTION_WEIGHT * INSERTION_WEIGHT
        for sgn in ((1.0, -1.0) if self._sign_first > 0 else (-1.0, 1.0)):
            x5x, x5y, x5z = sgn * nbx, sgn * nby, sgn * nbz
            wx, wy, wz = px - LW * x5x, py - LW * x5y, pz - LW * x5z
            dist = math.sqrt(wx * wx + wy * wy + wz * wz)
            if dist < _EPS:
                continue
            for L in (-dist, dist):
                d3 = L - D4
                if lim is not None and not lim.ok(2, d3):
                    continue
                ux, uy, uz = wx / L, wy / L, wz / L
                # v = RotX(a0)^T u
                vx, vy, vz = ux, ca[0] * uy + sa[0] * uz, -sa[0] * uy + ca[0] * uz
                c2 = (cc - vz) / denom
                if c2 > 1.0:
                    if c2 > 1.0 + 1e-9:
                        continue
                    c2 = 1.0
                elif c2 < -1.0:
                    if c2 < -1.0 - 1e-9:
                        continue
                    c2 = -1.0
                a2 = math.acos(c2)
                for th2 in ((a2, -a2) if a2 > 0.0 else (a2,)):
                    q1 = _wrap_near(th2 - off[1], s1)
                    if lim is not None and not lim.ok(1, q1):
                        continue
                    s2 = math.sin(th2)
                    mx = s2 * sa[2]
                    my = -ca[1] * c2 * sa[2] - sa[1] * ca[2]
                    if math.hypot(mx, my) < _EPS:
                        continue
                    th1 = math.atan2(vy, vx) - math.atan2(my, mx)
                    q0 = _wrap_near(th1 - off[0], s0)
                    if lim is not None and not lim.ok(0, q0):
                        continue
                    cost = 0.0
                    if seed is not None:
                        cost = (q0 - s0) ** 2 + (q1 - s1) ** 2 + w2 * (d3 - seed[2]) ** 2
                        if bound is not None and cost >= bound[0]:
                            continue
                    w = self._wrist(th1, th2, T, (x5x, x5y, x5z))
                    if w is None:
                        continue
                    th4, th5, th6 = w
                    if seed is None:
                        q = [q0, q1, d3, _wrap_near(th4 - off[3], 0.0), _wrap_near(th5 - off[4], 0.0),
                             _wrap_near(th6 - off[5], 0.0), sgn]
                    else:
                        q = [q0, q1, d3, _wrap_near(th4 - off[3], seed[3]), _wrap_near(th5 - off[4], seed[4]),
                             _wrap_near(th6 - off[5], seed[5]), sgn]
                        if lim is not None and not (lim.ok(3, q[3]) and lim.ok(4, q[4]) and lim.ok(5, q[5])):
                            continue
                        cost += (q[3] - seed[3]) ** 2 + (q[4] - seed[4]) ** 2 + (q[5] - seed[5]) ** 2
                    yield q, cost

    def _wrist(self, th1, th2, T, x5):
        """th4, th5, th6 given the positioning joints, the pose and the x5 axis (base frame)."""
        ca, sa = self._ca, self._sa
        # R03 columns via the same chain as fk (rotation only)
        x0, x1, x2 = 1.0, 0.0, 0.0
        y0, y1, y2 = 0.0, 1.0, 0.0
        z0, z1, z2 = 0.0, 0.0, 1.0
        for i, th in ((0, th1), (1, th2), (2, self.arm.theta3)):
            c, s = ca[i], sa[i]
            y0, y1, y2, z0, z1, z2 = (c * y0 + s * z0, c * y1 + s * z1, c * y2 + s * z2,
                                      -s * y0 + c * z0, -s * y1 + c * z1, -s * y2 + c * z2)
            ct, st = math.cos(th), math.sin(th)
            x0, x1, x2, y0, y1, y2 = (ct * x0 + st * y0, ct * x1 + st * y1, ct * x2 + st * y2,
                                      -st * x0 + ct * y0, -st * x1 + ct * y1, -st * x2 + ct * y2)
        # x5 and z6 in frame 3 (R03^T v: dot with the columns)
        ex, ey, ez = x5
        x5_3 = (x0 * ex + x1 * ey + x2 * ez, y0 * ex + y1 * ey + y2 * ez, z0 * ex + z1 * ey + z2 * ez)
        zx, zy, zz = T[0][2], T[1][2], T[2][2]  # T: nested lists
        z6_3 = (x0 * zx + x1 * zy + x2 * zz, y0 * zx + y1 * zy + y2 * zz, z0 * zx + z1 * zy + z2 * zz)
        # x5_3 = (c4 c5, s4 c5, s5); z6_3 = (c4 s5, s4 s5, -c5)
        s5, c5 = x5_3[2], -z6_3[2]
        th5 = math.atan2(s5, c5)
        c4 = c5 * x5_3[0] + s5 * z6_3[0]
        s4 = c5 * x5_3[1] + s5 * z6_3[1]
        if math.hypot(c4, s4) < 1e-6:
            return None
        th4 = math.atan2(s4, c4)
        # R05 = R03 RotZ(th4) RotX(pi/2) RotZ(th5): its x and z columns; R56 = R05^T R06,
        # R56 = [[c6, -s6, 0], [0, 0, -1], [s6, c6, 0]]: c6 = x5 . x6, s6 = z5 . x6
        c4_, s4_ = math.cos(th4), math.sin(th4)
        # frame 4 columns
        a0, a1, a2 = c4_ * x0 + s4_ * y0, c4_ * x1 + s4_ * y1, c4_ * x2 + s4_ * y2       # x4
        b0, b1, b2 = -s4_ * x0 + c4_ * y0, -s4_ * x1 + c4_ * y1, -s4_ * x2 + c4_ * y2    # y4
        # RotX(pi/2): y' = z, z' = -y ; then RotZ(th5) on x: x5 = c5 x4 + s5 z4
        c5_, s5_ = math.cos(th5), math.sin(th5)
        x5b = (c5_ * a0 + s5_ * z0, c5_ * a1 + s5_ * z1, c5_ * a2 + s5_ * z2)
        z5b = (-b0, -b1, -b2)
        xx, xy, xz = T[0][0], T[1][0], T[2][0]
        c6 = x5b[0] * xx + x5b[1] * xy + x5b[2] * xz
        s6 = z5b[0] * xx + z5b[1] * xy + z5b[2] * xz
        th6 = math.atan2(s6, c6)
        return th4, th5, th6


def _rows(T) -> list:
    """The first three rows of a 4x4 as nested Python lists (cheap scalar access)."""
    return T.tolist() if isinstance(T, np.ndarray) else [list(r) for r in T]


class _Limits:
    """Joint-limit checks for IK pruning; remembers the smallest violation for the error message."""

    __slots__ = ("lo", "hi", "msg", "excess")

    def __init__(self, lower, upper):
        self.lo = [x - 1e-9 for x in lower]
        self.hi = [x + 1e-9 for x in upper]
        self.msg = None
        self.excess = math.inf

    def ok(self, i: int, v: float) -> bool:
        lo, hi = self.lo[i], self.hi[i]
        if lo <= v <= hi:
            return True
        e = lo - v if v < lo else v - hi
        if e < self.excess:
            self.excess = e
            self.msg = (f"joint {JOINT_NAMES[i]!r} would be {v:.6g}, outside "
                        f"[{lo + 1e-9:.6g}, {hi - 1e-9:.6g}]")
        return False
