/* pointfence's compiled tick core, its orientation part: unit quaternions (w, x, y, z) of the
 * masters, the commands and the robots, and the poses built from them. Included by tick_core.c
 * (one translation unit; native/build.py hashes both files), never compiled on its own.
 * Uses <math.h>, <stdint.h> and PF_TINY, which tick_core.c has before it includes this. */
#ifndef PF_TICK_QUAT_H
#define PF_TICK_QUAT_H

/* --- unit quaternions (w, x, y, z): orientations of masters, commands and robots ------------- */

/* how far a master's quaternion norm may stray from 1 before its sample is invalid */
#define PF_QUAT_TOL 1e-3

/* out = a b (Hamilton product; out may alias neither a nor b) */
static void qmul(const double *a, const double *b, double *out) {
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

static void qconj(const double *a, double *out) { out[0] = a[0]; out[1] = -a[1]; out[2] = -a[2]; out[3] = -a[3]; }

static void copy4(double *dst, const double *src) { dst[0] = src[0]; dst[1] = src[1]; dst[2] = src[2]; dst[3] = src[3]; }

/* q scaled to unit norm, with w >= 0 (one representative of each rotation); identity if q is ~0 */
static void qunit(double *q) {
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (!(n > PF_TINY)) { q[0] = 1.0; q[1] = 0.0; q[2] = 0.0; q[3] = 0.0; return; }
    double f = q[0] < 0.0 ? -1.0 / n : 1.0 / n;
    q[0] *= f; q[1] *= f; q[2] *= f; q[3] *= f;
}

/* the rotation angle (rad, [0, pi]) of unit quaternion q */
static double qangle(const double *q) {
    double v = sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    return 2.0 * atan2(v, fabs(q[0]));
}

/* the angle (rad) between unit quaternions a and b */
static double qdist(const double *a, const double *b) {
    double c[4], d[4];
    qconj(b, c);
    qmul(a, c, d);
    return qangle(d);
}

/* the unit quaternion of rotation matrix R (row-major 3x3, rows `stride` doubles apart:
 * 3 for a 3x3, 4 for the rotation of a 4x4 pose); Shepperd's method */
static void quat_of_matrix(const double *T, int64_t stride, double *q) {
    const double r00 = T[0], r01 = T[1], r02 = T[2];
    const double r10 = T[stride], r11 = T[stride + 1], r12 = T[stride + 2];
    const double r20 = T[2 * stride], r21 = T[2 * stride + 1], r22 = T[2 * stride + 2];
    const double tr = r00 + r11 + r22;
    if (tr >= r00 && tr >= r11 && tr >= r22) {
        double s = 2.0 * sqrt(1.0 + tr);
        q[0] = 0.25 * s; q[1] = (r21 - r12) / s; q[2] = (r02 - r20) / s; q[3] = (r10 - r01) / s;
    } else if (r00 >= r11 && r00 >= r22) {
        double s = 2.0 * sqrt(1.0 + r00 - r11 - r22);
        q[0] = (r21 - r12) / s; q[1] = 0.25 * s; q[2] = (r01 + r10) / s; q[3] = (r02 + r20) / s;
    } else if (r11 >= r22) {
        double s = 2.0 * sqrt(1.0 + r11 - r00 - r22);
        q[0] = (r02 - r20) / s; q[1] = (r01 + r10) / s; q[2] = 0.25 * s; q[3] = (r12 + r21) / s;
    } else {
        double s = 2.0 * sqrt(1.0 + r22 - r00 - r11);
        q[0] = (r10 - r01) / s; q[1] = (r02 + r20) / s; q[2] = (r12 + r21) / s; q[3] = 0.25 * s;
    }
    qunit(q);
}

/* the rotation matrix of unit quaternion q into rows `stride` doubles apart */
static void matrix_of_quat(const double *q, double *T, int64_t stride) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    T[0] = 1.0 - 2.0 * (y * y + z * z); T[1] = 2.0 * (x * y - w * z); T[2] = 2.0 * (x * z + w * y);
    T += stride;
    T[0] = 2.0 * (x * y + w * z); T[1] = 1.0 - 2.0 * (x * x + z * z); T[2] = 2.0 * (y * z - w * x);
    T += stride;
    T[0] = 2.0 * (x * z - w * y); T[1] = 2.0 * (y * z + w * x); T[2] = 1.0 - 2.0 * (x * x + y * y);
}

/* n unit quaternions (n, 4) of n rotations: 4x4 poses (stride 4, 16 doubles each) or 3x3 (stride 3) */
void pf_quats_of_matrices(const double *T, int64_t stride, int64_t n, double *q) {
    const int64_t step = stride == 4 ? 16 : 9;
    for (int64_t i = 0; i < n; i++) quat_of_matrix(T + step * i, stride, q + 4 * i);
}

/* n 4x4 poses (n, 16) from positions (n, 3) and unit quaternions (n, 4) */
void pf_poses_of(const double *p, const double *q, int64_t n, double *T) {
    for (int64_t i = 0; i < n; i++) {
        double *t = T + 16 * i;
        double u[4];
        copy4(u, q + 4 * i);
        qunit(u);
        matrix_of_quat(u, t, 4);
        t[3] = p[3 * i]; t[7] = p[3 * i + 1]; t[11] = p[3 * i + 2];
        t[12] = 0.0; t[13] = 0.0; t[14] = 0.0; t[15] = 1.0;
    }
}

/* A 4x4 pose (row-major, 16 doubles) checked as robot/base.py's ``as_pose`` does: 0 for a
 * finite rigid transform with a proper rotation; 1 not finite; 2 last row not [0 0 0 1] within
 * ``tol``; 3 rotation not orthonormal (max |R^T R - I| > tol); 4 a reflection (det < 0). The
 * robot's setpoint check calls it every tick; Python names what is wrong only when it fails. */
int32_t pf_pose_check(const double *T, double tol) {
    double s = 0.0;
    for (int i = 0; i < 16; i++) s += T[i];
    if (!isfinite(s)) return 1;
    const double r00 = T[0], r01 = T[1], r02 = T[2], r10 = T[4], r11 = T[5], r12 = T[6];
    const double r20 = T[8], r21 = T[9], r22 = T[10];
    if (fmax(fmax(fabs(T[12]), fabs(T[13])), fmax(fabs(T[14]), fabs(T[15] - 1.0))) > tol) return 2;
    double err = fabs(r00 * r00 + r10 * r10 + r20 * r20 - 1.0);
    err = fmax(err, fabs(r01 * r01 + r11 * r11 + r21 * r21 - 1.0));
    err = fmax(err, fabs(r02 * r02 + r12 * r12 + r22 * r22 - 1.0));
    err = fmax(err, fabs(r00 * r01 + r10 * r11 + r20 * r21));
    err = fmax(err, fabs(r00 * r02 + r10 * r12 + r20 * r22));
    err = fmax(err, fabs(r01 * r02 + r11 * r12 + r21 * r22));
    if (err > tol) return 3;
    const double det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20);
    return det < 0.0 ? 4 : 0;
}

/* Every master's position (3) and orientation (4) from its own arrays (pos_src[i], quat_src[i])
 * into the tick's (n, 3) and (n, 4) arrays. */
static void pf_masters_gather(const double *const *pos_src, const double *const *quat_src, int64_t n, double *pos,
                       double *quat) {
    for (int64_t i = 0; i < n; i++) {
        memcpy(pos + 3 * i, pos_src[i], 3 * sizeof(double));
        memcpy(quat + 4 * i, quat_src[i], 4 * sizeof(double));
    }
}

/* A master sample is valid only if the device says so and its position, orientation (a unit
 * quaternion within PF_QUAT_TOL) and grasp are finite: ok[i] is cleared otherwise (S2). */
static void pf_masters_valid(const double *pos, const double *quat, const double *grasp, int64_t n, uint8_t *ok) {
    for (int64_t i = 0; i < n; i++) {
        const double *p = pos + 3 * i, *q = quat + 4 * i;
        int finite = isfinite(p[0]) && isfinite(p[1]) && isfinite(p[2]) && isfinite(grasp[i]);
        double qn = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (!finite || !(fabs(qn - 1.0) <= PF_QUAT_TOL)) ok[i] = 0;   /* (a NaN fails the compare) */
    }
}

/* Every master's force (3, row i of the tick's (n, 3) forces) into its own array dst[i] (the
 * masters that only store the force they are sent: service/devices.py Devices.send_forces). */
void pf_masters_scatter(const double *force, int64_t n, double *const *dst) {
    for (int64_t i = 0; i < n; i++) memcpy(dst[i], force + 3 * i, 3 * sizeof(double));
}

/* The tick's master samples in one call: pf_masters_gather, then pf_masters_valid. */
void pf_masters_take(const double *const *pos_src, const double *const *quat_src, int64_t n, double *pos,
                     double *quat, const double *grasp, uint8_t *ok) {
    pf_masters_gather(pos_src, quat_src, n, pos, quat);
    pf_masters_valid(pos, quat, grasp, n, ok);
}

/* A scripted trajectory at script time s (service/masters.py ScriptedMaster.poll): times t (n,)
 * increasing, positions p (n, 3), steps d (n - 1, 3) = p[i + 1] - p[i]. Writes the position
 * into pos (3) and into wk = (w, finite): w the interpolation weight between samples i and i + 1,
 * -1 at or outside the ends (the end sample holds), finite 1 if the position is. Returns i: the
 * sample at or before s (bisect_right's, so that NaN and ties fall as in Python), 0 before the
 * first, n - 1 at or after the last. Same float64 arithmetic as Python's d * w + p (no FMA). */
int64_t pf_script_at(const double *t, const double *p, const double *d, int64_t n, double s, double *pos,
                     double *wk) {
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        const int64_t mid = (lo + hi) / 2;
        if (s < t[mid]) hi = mid;
        else lo = mid + 1;
    }
    int64_t i = lo - 1;
    double w = -1.0;
    if (i < 0) {
        i = 0;
        memcpy(pos, p, 3 * sizeof(double));
    } else if (i >= n - 1) {
        i = n - 1;
        memcpy(pos, p + 3 * i, 3 * sizeof(double));
    } else {
        w = (s - t[i]) / (t[i + 1] - t[i]);
        for (int k = 0; k < 3; k++) pos[k] = d[3 * i + k] * w + p[3 * i + k];
    }
    wk[0] = w;
    wk[1] = isfinite(pos[0] + pos[1] + pos[2]) ? 1.0 : 0.0;
    return i;
}

#endif
