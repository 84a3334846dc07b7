/* pointfence's compiled tick core: the per-tick arithmetic of the 1 kHz haptic tick.
 *
 * One implementation, called from Python through ctypes (native/__init__.py declares every
 * struct and function below; keep the two in step). The Python classes own the arrays
 * (NumPy, allocated once) and hold one of these structs with pointers into them:
 *
 *   pf_teleop  service/teleop.py    Teleop: clutch, indexing, architectures, speed limit,
 *                                   orientation (unit quaternions w x y z) and jaw
 *   pf_health  service/health.py    Health: which arms hold this tick and why
 *   pf_forces  kernels/forces.py    ForceRenderer: spring, damping, FIR, saturation
 *   pf_step    service/app.py       Service.step: couples the three around the proxy kernel
 *
 * Units: positions in metres (world frame unless said otherwise), forces in newtons, times in
 * seconds. Arrays of B arms are row-major: (B, 3) doubles, (B,) bytes for booleans (0 or 1).
 * Nothing here allocates, blocks or does I/O. Floating-point expressions are evaluated in the
 * order written (the library is built with -ffp-contract=off): results are the same on every
 * run and every machine of the same architecture.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define PF_TINY 1e-12

/* --- small vector helpers ---------------------------------------------------------------- */

static double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

/* out = R v (R row-major 3x3) */
static void rot3(const double *R, const double *v, double *out) {
    out[0] = R[0] * v[0] + R[1] * v[1] + R[2] * v[2];
    out[1] = R[3] * v[0] + R[4] * v[1] + R[5] * v[2];
    out[2] = R[6] * v[0] + R[7] * v[1] + R[8] * v[2];
}

/* out = R^T v */
static void rot3t(const double *R, const double *v, double *out) {
    out[0] = R[0] * v[0] + R[3] * v[1] + R[6] * v[2];
    out[1] = R[1] * v[0] + R[4] * v[1] + R[7] * v[2];
    out[2] = R[2] * v[0] + R[5] * v[1] + R[8] * v[2];
}

static void copy3(double *dst, const double *src) { dst[0] = src[0]; dst[1] = src[1]; dst[2] = src[2]; }

static void copy3f(double *dst, const float *src) {
    dst[0] = (double)src[0]; dst[1] = (double)src[1]; dst[2] = (double)src[2];
}

/* scale v down to `length` when it is longer (direction kept) */
static void clamp3(double *v, double length) {
    double n = norm3(v);
    double f = n > length ? n : length;
    if (f < PF_TINY) f = PF_TINY;
    f = length / f;
    if (f > 1.0) f = 1.0;
    v[0] *= f; v[1] *= f; v[2] *= f;
}

/* shorten v by `length` (a shorter v becomes zero) */
static void shrink3(double *v, double length) {
    double n = norm3(v);
    if (n < PF_TINY) n = PF_TINY;
    double f = 1.0 - length / n;
    if (f < 0.0) f = 0.0;
    v[0] *= f; v[1] *= f; v[2] *= f;
}

#include "tick_quat.h"
#include "neighbor_rows.h"

/* --- teleoperation (service/teleop.py) ---------------------------------------------------- */

typedef struct {
    int64_t n;
    double R[9];            /* registration: world <- master rotation, row-major */
    double p[3];            /* registration: master origin in the world, m */
    double scale;           /* robot motion per master motion */
    double vmax;            /* command (and HIP blend) speed bound, m/s */
    double dt;              /* tick period, s */
    double anchor_release;  /* master motion (world, scaled, m) that ends an anchoring */
    int32_t arch;           /* 1, 2, 3: architectures I, II, III */
    int32_t rebase;         /* next update_hip keeps the HIP continuous */
    int32_t blending;       /* e_hip may be non-zero */
    int32_t anchoring;      /* some arm is anchored */
    double *dev_prev;       /* (B,3) last valid master sample, master frame */
    double *X_m;            /* (B,3) mapped master point */
    double *hip;            /* (B,3) HIP used this tick */
    double *e_hip;          /* (B,3) HIP blend offset */
    double *target;         /* (B,3) the HIP's target without the blend offset */
    double *cmd;            /* (B,3) robot command X_r* */
    double *goal;           /* (B,3) command goal before the rate limit */
    double *moved;          /* (B,) master motion since the arm was anchored, m */
    uint8_t *live;          /* (B,) sample valid and pedal down on the last tick */
    uint8_t *anchored;      /* (B,) re-anchored arms whose command stays put */
    double slip_lift;       /* III: radius of the slip lift, m (the fixture radius; 0: no lift) */
    const float *normals;   /* (B,3) the proxies' surface normals (zero: none), or NULL */
    /* orientation (unit quaternions w, x, y, z) and the jaw */
    double wmax;            /* orientation command speed bound, rad/s */
    double jaw_vmax;        /* jaw command speed bound, rad/s */
    double anchor_release_rad;   /* master rotation (rad) that ends an anchoring */
    double qR[4];           /* registration: world <- master rotation */
    double *q_last;         /* (B,4) last valid master orientation, master frame */
    double *q_off;          /* (B,4) indexing offset: q_m = qR q_dev q_off */
    double *q_m;            /* (B,4) mapped master orientation, world */
    double *q_cmd;          /* (B,4) commanded tool orientation, world */
    double *ang_moved;      /* (B,) master rotation since the arm was anchored, rad */
    double *grasp;          /* (B,) last valid master grasp, rad */
    double *jaw_cmd;        /* (B,) jaw command, rad (NaN: the jaw's angle is unknown: not commanded) */
    const double *jaw_lo;   /* (B,) the robot's jaw range, rad */
    const double *jaw_hi;
    double *jaw_side;       /* (B,) sign of (grasp - jaw) while the jaw waits, 0: not known yet */
    uint8_t *jaw_wait;      /* (B,) the jaw waits for the grasp to reach it (after a re-anchor) */
} pf_teleop;

void pf_teleop_map_masters(pf_teleop *tp, const double *dev, const double *quat, const double *grasp,
                           const uint8_t *pedal, const uint8_t *ok) {
    int any = 0;
    for (int64_t i = 0; i < tp->n; i++) {
        const double *d_now = dev + 3 * i;
        double *d_prev = tp->dev_prev + 3 * i;
        int act = pedal[i] && ok[i];
        int both = act && tp->live[i];       /* active now and on the last tick */
        tp->live[i] = (uint8_t)act;
        double d[3] = {0.0, 0.0, 0.0}, w[3];
        if (both) { d[0] = d_now[0] - d_prev[0]; d[1] = d_now[1] - d_prev[1]; d[2] = d_now[2] - d_prev[2]; }
        rot3(tp->R, d, w);
        w[0] *= tp->scale; w[1] *= tp->scale; w[2] *= tp->scale;
        /* orientation: the registered master orientation qw = qR q_dev, the mapped one qw q_off */
        double qd[4], qw[4], q_new[4], ang = 0.0;
        double *qm = tp->q_m + 4 * i, *qo = tp->q_off + 4 * i;
        if (act) {
            copy4(qd, quat + 4 * i);
            qunit(qd);
            qmul(tp->qR, qd, qw);
            qmul(qw, qo, q_new);
            qunit(q_new);
            if (both) ang = qdist(q_new, qm);
        }
        if (tp->anchoring) {     /* an anchored arm's X_m stays on its command; its motion only counts */
            tp->moved[i] += norm3(w);
            tp->ang_moved[i] += ang;
            tp->anchored[i] = (uint8_t)(tp->anchored[i] && tp->moved[i] < tp->anchor_release &&
                                        tp->ang_moved[i] < tp->anchor_release_rad);
            if (tp->anchored[i]) { w[0] = 0.0; w[1] = 0.0; w[2] = 0.0; }
            any |= tp->anchored[i];
        }
        double *x = tp->X_m + 3 * i;
        x[0] += w[0]; x[1] += w[1]; x[2] += w[2];
        if (act) {
            if (both && !tp->anchored[i]) {
                copy4(qm, q_new);
            } else {             /* indexing: q_m stays, the offset takes up the master's rotation */
                double c[4];
                qconj(qw, c);
                qmul(c, qm, qo);
                qunit(qo);
            }
        }
        if (ok[i]) {
            copy3(d_prev, d_now);
            copy4(tp->q_last + 4 * i, quat + 4 * i);
            qunit(tp->q_last + 4 * i);
            tp->grasp[i] = grasp[i];
        }
    }
    if (tp->anchoring) tp->anchoring = any;
}

/* the HIP by architecture (X_r in II, X_m otherwise) plus the decaying blend offset */
void pf_teleop_update_hip(pf_teleop *tp, const double *xr) {
    const double *src = tp->arch == 2 ? xr : tp->X_m;
    memmove(tp->target, src, sizeof(double) * 3 * (size_t)tp->n);
    if (tp->rebase) {
        for (int64_t j = 0; j < 3 * tp->n; j++) tp->e_hip[j] = tp->hip[j] - tp->target[j];
        tp->rebase = 0;
        tp->blending = 1;
    }
    if (tp->blending) {
        int any = 0;
        for (int64_t i = 0; i < tp->n; i++) {
            double *e = tp->e_hip + 3 * i;
            shrink3(e, tp->vmax * tp->dt);
            any |= (e[0] != 0.0) | (e[1] != 0.0) | (e[2] != 0.0);
        }
        tp->blending = any;
        for (int64_t j = 0; j < 3 * tp->n; j++) tp->hip[j] = tp->target[j] + tp->e_hip[j];
    } else {
        memcpy(tp->hip, tp->target, sizeof(double) * 3 * (size_t)tp->n);
    }
}

/* where the proxies move: the target itself in III (the proxy is the robot's goal), the HIP otherwise */
const double *pf_teleop_proxy_hip(const pf_teleop *tp) { return tp->arch == 3 ? tp->target : tp->hip; }

/* X_r* before the rate limit: the proxy in III while rendering, X_m otherwise.
 * III's slip lift (slip_lift > 0 and normals bound): a proxy that slips over a noisy cloud jumps
 * sideways faster than the rate-limited command follows, and the straight path from the command
 * to it cuts through the bumps between them. The goal is raised along the proxy's surface normal
 * n by min(L^2 / slip_lift, slip_lift), L the command's distance to the proxy across n: nothing
 * while the command keeps up with the proxy (L ~ 0), up to one fixture radius over a slip, so the
 * command lifts off, crosses, and lands on the proxy as L shrinks. */
void pf_teleop_command_goal(pf_teleop *tp, const float *proxies, int32_t haptics_running) {
    if (tp->arch == 3 && haptics_running) {
        for (int64_t i = 0; i < tp->n; i++) {
            double *g = tp->goal + 3 * i;
            copy3f(g, proxies + 3 * i);
            if (tp->slip_lift <= 0.0 || tp->normals == NULL) continue;
            double nv[3] = {tp->normals[3 * i], tp->normals[3 * i + 1], tp->normals[3 * i + 2]};
            double nn = norm3(nv);
            if (!(nn > 0.5)) continue;                    /* no surface estimate: no lift */
            nv[0] /= nn; nv[1] /= nn; nv[2] /= nn;
            const double *c = tp->cmd + 3 * i;
            double e[3] = {g[0] - c[0], g[1] - c[1], g[2] - c[2]};
            double en = e[0] * nv[0] + e[1] * nv[1] + e[2] * nv[2];
            double t0 = e[0] - en * nv[0], t1 = e[1] - en * nv[1], t2 = e[2] - en * nv[2];
            double h = (t0 * t0 + t1 * t1 + t2 * t2) / tp->slip_lift;
            if (h > tp->slip_lift) h = tp->slip_lift;
            g[0] += h * nv[0]; g[1] += h * nv[1]; g[2] += h * nv[2];
        }
    } else {
        memcpy(tp->goal, tp->X_m, sizeof(double) * 3 * (size_t)tp->n);
    }
}

/* arm i's orientation re-seated on its command: q_m = q_cmd, and the offset such that the
 * master's last sample maps onto it; its jaw waits for the grasp to reach it */
static void seat_orientation(pf_teleop *tp, int64_t i) {
    double *qm = tp->q_m + 4 * i, *qo = tp->q_off + 4 * i;
    double qw[4], c[4];
    copy4(qm, tp->q_cmd + 4 * i);
    qmul(tp->qR, tp->q_last + 4 * i, qw);
    qconj(qw, c);
    qmul(c, qm, qo);
    qunit(qo);
    tp->jaw_wait[i] = 1;
    tp->jaw_side[i] = 0.0;
}

static void anchor(pf_teleop *tp, const uint8_t *mask) {
    int any = 0;
    for (int64_t i = 0; i < tp->n; i++) {
        if (mask == NULL || mask[i]) {
            tp->anchored[i] = 1; tp->moved[i] = 0.0; tp->ang_moved[i] = 0.0;
            seat_orientation(tp, i);
        }
        any |= tp->anchored[i];
    }
    tp->anchoring = any;
}

/* indexing for the arms in mask: X_m shifts by (command - goal); the goal becomes the command;
 * the orientation offset is re-seated so that the mapped orientation is the commanded one */
void pf_teleop_reanchor(pf_teleop *tp, const uint8_t *mask) {
    for (int64_t i = 0; i < tp->n; i++) {
        if (!mask[i]) continue;
        for (int c = 0; c < 3; c++) {
            int64_t j = 3 * i + c;
            tp->X_m[j] += tp->cmd[j] - tp->goal[j];
            tp->goal[j] = tp->cmd[j];
        }
    }
    anchor(tp, mask);
    tp->rebase = 1;
}

/* a change of control law: every arm's X_m and goal move onto its command, its orientation too */
void pf_teleop_reanchor_all(pf_teleop *tp) {
    memcpy(tp->X_m, tp->cmd, sizeof(double) * 3 * (size_t)tp->n);
    memcpy(tp->goal, tp->cmd, sizeof(double) * 3 * (size_t)tp->n);
    anchor(tp, NULL);
    tp->rebase = 1;
}

/* arm i's jaw towards the master's grasp (clamped to the jaw's range) by at most jaw_vmax * dt,
 * once the grasp has reached the jaw after a re-anchor (it crossed it, or came within a step) */
static void limit_jaw(pf_teleop *tp, int64_t i) {
    double j = tp->jaw_cmd[i], g = tp->grasp[i];
    if (!isfinite(j) || !isfinite(g)) return;
    if (g < tp->jaw_lo[i]) g = tp->jaw_lo[i];
    if (g > tp->jaw_hi[i]) g = tp->jaw_hi[i];
    double diff = g - j, step = tp->jaw_vmax * tp->dt;
    if (tp->jaw_wait[i]) {
        double side = tp->jaw_side[i];
        if (fabs(diff) <= step || (side != 0.0 && diff * side < 0.0)) tp->jaw_wait[i] = 0;
        else { tp->jaw_side[i] = diff > 0.0 ? 1.0 : -1.0; return; }
    }
    if (diff > step) diff = step;
    if (diff < -step) diff = -step;
    tp->jaw_cmd[i] = j + diff;
}

/* arm i's commanded orientation towards q_m by at most wmax * dt (rad) */
static void limit_orientation(pf_teleop *tp, int64_t i) {
    double *qc = tp->q_cmd + 4 * i;
    double c[4], d[4];
    qconj(qc, c);
    qmul(tp->q_m + 4 * i, c, d);        /* the rotation from the command to the goal (world) */
    qunit(d);
    double v = sqrt(d[1] * d[1] + d[2] * d[2] + d[3] * d[3]);
    double ang = 2.0 * atan2(v, d[0]), lim = tp->wmax * tp->dt;
    if (ang > lim) {
        double f = sin(0.5 * lim) / v;
        d[0] = cos(0.5 * lim); d[1] *= f; d[2] *= f; d[3] *= f;
    }
    double out[4];
    qmul(d, qc, out);
    qunit(out);
    copy4(qc, out);
}

/* the command of coupled, unanchored arms moves towards the goal by at most vmax * dt, their
 * orientation towards q_m by at most wmax * dt; the jaw of coupled arms follows the grasp */
void pf_teleop_limit_command(pf_teleop *tp, const uint8_t *coupled) {
    for (int64_t i = 0; i < tp->n; i++) {
        if (!coupled[i]) continue;
        limit_jaw(tp, i);
        if (tp->anchored[i]) continue;
        double *c = tp->cmd + 3 * i;
        const double *g = tp->goal + 3 * i;
        double d[3] = {g[0] - c[0], g[1] - c[1], g[2] - c[2]};
        clamp3(d, tp->vmax * tp->dt);
        c[0] += d[0]; c[1] += d[1]; c[2] += d[2];
        limit_orientation(tp, i);
    }
}

/* --- health (service/health.py) ----------------------------------------------------------- */

typedef struct {
    int64_t n;
    int64_t reasons;         /* global reasons (rows of seen) */
    double recover_s;        /* how long a condition must be clear, s */
    int64_t master_bit;      /* HoldReason.MASTER */
    int64_t robot_bit;       /* HoldReason.ROBOT */
    int64_t latched;         /* latched reasons until cleared */
    int64_t mask;            /* this tick's reasons for every arm */
    const int64_t *bits;     /* (reasons,) the global reasons' bits */
    double *seen;            /* (reasons,) loop time each global reason was last seen */
    double *master_seen;     /* (B,) per arm: master invalid */
    double *robot_seen;      /* (B,) per arm: robot fault or refused command */
    int64_t *arm;            /* (B,) this tick's reasons per arm */
    uint8_t *arm_ok;         /* (B,) no reason to hold */
} pf_health;

void pf_health_assess(pf_health *h, double t, const uint8_t *master_ok, const uint8_t *robot_fault) {
    int64_t hold = h->latched;
    for (int64_t r = 0; r < h->reasons; r++)
        if (t - h->seen[r] < h->recover_s) hold |= h->bits[r];
    h->mask = hold;
    for (int64_t i = 0; i < h->n; i++) {
        if (!master_ok[i]) h->master_seen[i] = t;
        if (robot_fault[i]) h->robot_seen[i] = t;
        int64_t a = hold;
        if (t - h->master_seen[i] < h->recover_s) a |= h->master_bit;
        if (t - h->robot_seen[i] < h->recover_s) a |= h->robot_bit;
        h->arm[i] = a;
        h->arm_ok[i] = (uint8_t)(a == 0);
    }
}

/* every arm holds for `reason` from now on in this tick */
void pf_health_hold_all(pf_health *h, int64_t reason) {
    h->mask |= reason;
    for (int64_t i = 0; i < h->n; i++) { h->arm[i] |= reason; h->arm_ok[i] = 0; }
}

/* --- forces (kernels/forces.py) ------------------------------------------------------------ */

typedef struct {
    int64_t n;               /* proxies */
    int64_t cap;             /* row stride of hist (proxies it has room for) */
    int64_t taps_n;          /* FIR length T */
    int64_t head;            /* ring row of the next raw force */
    int32_t have_prev;       /* prev holds last tick's HIPs */
    int32_t free_state;      /* the proxy state FREE */
    double dead_band, stiffness, b, rate_hz, max_force;
    const double *taps;      /* (T,) taps[0] weighs the newest raw force */
    double *hist;            /* (T, cap * 3) ring of raw forces */
    double *prev;            /* (cap, 3) last tick's HIPs */
    double *raw;             /* (cap, 3) spring + damping before the filter, N */
    double *forces;          /* (cap, 3) filtered, saturated, N */
    uint8_t *sat;            /* (cap,) saturated this tick */
} pf_forces;

void pf_forces_reset(pf_forces *f) {
    memset(f->hist, 0, sizeof(double) * (size_t)(f->taps_n * f->cap * 3));
    memset(f->forces, 0, sizeof(double) * (size_t)(f->cap * 3));
    memset(f->raw, 0, sizeof(double) * (size_t)(f->cap * 3));
    memset(f->sat, 0, (size_t)f->cap);
    f->head = 0;
    f->have_prev = 0;
}

static int finite_rows(const void *a, int32_t is_f32, int64_t n) {
    for (int64_t j = 0; j < 3 * n; j++) {
        double x = is_f32 ? (double)((const float *)a)[j] : ((const double *)a)[j];
        if (!isfinite(x)) return 0;
    }
    return 1;
}

/* this tick's forces on the HIPs xh from proxy centres xp ((B,3) float32 if xp_f32, else
 * float64) and proxy states. Returns 0; 1 if xp, 2 if xh holds a non-finite value (nothing
 * changed then). */
int32_t pf_forces_update(pf_forces *f, const void *xp_any, int32_t xp_f32, const double *xh, const int32_t *states) {
    const int64_t n = f->n, T = f->taps_n;
    if (!finite_rows(xp_any, xp_f32, n)) return 1;
    if (!finite_rows(xh, 0, n)) return 2;
    const float *xp32 = (const float *)xp_any;
    const double *xp64 = (const double *)xp_any;
    const double db = f->dead_band, k = f->stiffness;
    const int damp = f->have_prev && f->b > 0.0;
    const double bk = f->b * f->rate_hz;
    double *ring = f->hist + f->head * f->cap * 3;
    for (int64_t i = 0; i < n; i++) {
        const double *h = xh + 3 * i;
        double q[3];
        if (xp_f32) copy3f(q, xp32 + 3 * i); else copy3(q, xp64 + 3 * i);
        double v[3] = {h[0] - q[0], h[1] - q[1], h[2] - q[2]};
        double d = norm3(v);
        int engaged = d > db;
        double dd = engaged ? d : db;
        double m = engaged ? (d - db) * k / dd : 0.0;     /* spring beyond the dead band */
        double F[3] = {-(v[0] * m), -(v[1] * m), -(v[2] * m)};
        if (damp && engaged && states[i] != f->free_state) {   /* damping during contact */
            const double *p = f->prev + 3 * i;
            F[0] -= (h[0] - p[0]) * bk;
            F[1] -= (h[1] - p[1]) * bk;
            F[2] -= (h[2] - p[2]) * bk;
            double dot = F[0] * v[0] + F[1] * v[1] + F[2] * v[2];   /* > 0: pulls the HIP inwards */
            if (dot > 0.0) {
                double c = dot / dd / dd;
                F[0] -= v[0] * c; F[1] -= v[1] * c; F[2] -= v[2] * c;
            }
        }
        copy3(f->raw + 3 * i, F);
        copy3(ring + 3 * i, F);
        copy3(f->prev + 3 * i, h);
    }
    f->have_prev = 1;
    /* FIR over the last T raw forces, oldest first */
    for (int64_t j = 0; j < 3 * n; j++) {
        double s = 0.0;
        for (int64_t a = T - 1; a >= 0; a--) {
            int64_t row = (f->head - a + T) % T;
            s += f->taps[a] * f->hist[row * f->cap * 3 + j];
        }
        f->forces[j] = s;
    }
    f->head = (f->head + 1) % T;
    /* saturation, keeping the direction */
    for (int64_t i = 0; i < n; i++) {
        double *F = f->forces + 3 * i;
        double l = norm3(F);
        f->sat[i] = (uint8_t)(l > f->max_force);
        if (f->sat[i]) {
            double s = f->max_force / l;
            F[0] *= s; F[1] *= s; F[2] *= s;
        }
    }
    return 0;
}

/* --- the step around the proxy kernel (service/app.py) ------------------------------------- */

typedef struct {
    int64_t n;
    /* the tick's input (TickInput) */
    const double *master_pos;    /* (B,3) master frame */
    const uint8_t *pedal;
    const uint8_t *master_ok;
    const double *robot_pos;     /* (B,3) measured */
    /* the service's state */
    uint8_t *coupled_prev;       /* coupled on the last tick */
    uint8_t *reseat;             /* this tick's arms whose proxy restarts */
    const uint8_t *present;      /* a robot is attached (else ideal: X_r = X_r*) */
    double *gain;                /* force gain per arm, [0, 1] */
    double *phip;                /* (B,3) where the proxies move this tick */
    /* the tick's output (TickOutput) */
    double *xm, *hip, *proxy, *force, *force_master, *gain_out, *command, *robot_pos_out;
    int32_t *state;
    uint8_t *coupled, *engage, *release;
    int64_t *arm_hold;
    /* orientation and jaw: the tick's input (TickInput) */
    const double *master_quat;   /* (B,4) master frame, w x y z */
    const double *grasp;         /* (B,) rad */
    const double *robot_quat;    /* (B,4) measured, world */
    const double *robot_jaw;     /* (B,) measured, rad (NaN: unknown) */
    /* ... and its output (TickOutput) */
    double *orientation;         /* (B,4) commanded tool orientation, world */
    double *jaw;                 /* (B,) jaw command, rad */
} pf_step;

/* Before the kernel: teleoperation, coupling and re-anchoring, the HIP and the proxy targets.
 * Returns 1 if some arm's proxy must be re-seated (reseat), else 0. */
int32_t pf_step_pre(pf_step *s, pf_teleop *tp, const pf_health *h, const float *proxies, int32_t law_change,
                    int32_t teleop_on) {
    const int64_t n = s->n;
    const uint8_t *ok = h->arm_ok;
    pf_teleop_map_masters(tp, s->master_pos, s->master_quat, s->grasp, s->pedal, ok);
    int engaged = 0;
    for (int64_t i = 0; i < n; i++) {
        s->coupled[i] = (uint8_t)(teleop_on && ok[i] && s->pedal[i]);
        s->engage[i] = (uint8_t)(s->coupled[i] && !s->coupled_prev[i]);
        engaged |= s->engage[i];
    }
    /* S1: an arm that (re)couples, and every arm at a change of control law, starts from its command */
    int reseat = 0;
    if (law_change) {
        memset(s->reseat, 1, (size_t)n);
        reseat = 1;
        pf_teleop_reanchor_all(tp);
    } else {
        memcpy(s->reseat, s->engage, (size_t)n);
        reseat = engaged;
        if (engaged) pf_teleop_reanchor(tp, s->engage);
    }
    for (int64_t i = 0; i < n; i++)        /* an ideal robot is where it is commanded */
        copy3(s->robot_pos_out + 3 * i, s->present[i] ? s->robot_pos + 3 * i : tp->cmd + 3 * i);
    pf_teleop_update_hip(tp, s->robot_pos_out);
    /* a held or unclutched arm's proxy stays where it is (in III it must not creep off the command) */
    const double *src = pf_teleop_proxy_hip(tp);
    for (int64_t i = 0; i < n; i++) {
        if (ok[i] && s->pedal[i]) copy3(s->phip + 3 * i, src + 3 * i);
        else copy3f(s->phip + 3 * i, proxies + 3 * i);
    }
    return reseat;
}

/* the rendered forces times each arm's gain, in the world frame and in each master's (R^T f) */
void pf_step_scale_forces(pf_step *s, const pf_teleop *tp, const pf_forces *f) {
    for (int64_t i = 0; i < s->n; i++) {
        double *F = s->force + 3 * i;
        const double *r = f->forces + 3 * i;
        s->gain_out[i] = s->gain[i];
        F[0] = r[0] * s->gain[i]; F[1] = r[1] * s->gain[i]; F[2] = r[2] * s->gain[i];
        rot3t(tp->R, F, s->force_master + 3 * i);
    }
}

/* After the kernel: the force gain ramp, the forces in the world and master frames, the robot
 * commands, coupling edges, and the output's copies of the components' state. */
void pf_step_post(pf_step *s, pf_teleop *tp, const pf_health *h, const pf_forces *f, const float *proxies,
                  const int32_t *states, int32_t haptics, double ramp) {
    const int64_t n = s->n;
    for (int64_t i = 0; i < n; i++) {
        /* the gain ramps towards 1 for a coupled arm with haptics engaged, towards 0 otherwise */
        double want = (haptics && h->arm_ok[i] && s->pedal[i]) ? 1.0 : 0.0;
        double g = want - s->gain[i];
        if (g < -ramp) g = -ramp;
        if (g > ramp) g = ramp;
        s->gain[i] += g;
    }
    pf_step_scale_forces(s, tp, f);
    pf_teleop_command_goal(tp, proxies, haptics);
    pf_teleop_limit_command(tp, s->coupled);
    for (int64_t i = 0; i < n; i++) {
        s->release[i] = (uint8_t)(s->coupled_prev[i] && !s->coupled[i]);
        if (s->release[i] && s->present[i]) {      /* a robot that decouples stops where it is */
            copy3(tp->cmd + 3 * i, s->robot_pos_out + 3 * i);
            copy4(tp->q_cmd + 4 * i, s->robot_quat + 4 * i);
            qunit(tp->q_cmd + 4 * i);
            tp->jaw_cmd[i] = s->robot_jaw[i];
        }
        if (s->coupled[i] && !s->present[i])
            copy3(s->robot_pos_out + 3 * i, tp->cmd + 3 * i);
        s->engage[i] = (uint8_t)(s->coupled[i] && !s->coupled_prev[i]);
        s->coupled_prev[i] = s->coupled[i];
        copy3f(s->proxy + 3 * i, proxies + 3 * i);
        s->state[i] = states[i];
        s->arm_hold[i] = h->arm[i];
    }
    memcpy(s->xm, tp->X_m, sizeof(double) * 3 * (size_t)n);
    memcpy(s->hip, tp->hip, sizeof(double) * 3 * (size_t)n);
    memcpy(s->command, tp->cmd, sizeof(double) * 3 * (size_t)n);
    memcpy(s->orientation, tp->q_cmd, sizeof(double) * 4 * (size_t)n);
    memcpy(s->jaw, tp->jaw_cmd, sizeof(double) * (size_t)n);
}

/* The output's positions, forces and states into another step's output (the copy other threads
 * read: Service.snapshot / status), under the caller's lock. */
void pf_step_publish(const pf_step *s, pf_step *dst) {
    const size_t b3 = sizeof(double) * 3 * (size_t)s->n;
    memcpy(dst->xm, s->xm, b3);
    memcpy(dst->hip, s->hip, b3);
    memcpy(dst->proxy, s->proxy, b3);
    memcpy(dst->command, s->command, b3);
    memcpy(dst->robot_pos_out, s->robot_pos_out, b3);
    memcpy(dst->force, s->force, b3);
    memcpy(dst->state, s->state, sizeof(int32_t) * (size_t)s->n);
    memcpy(dst->orientation, s->orientation, sizeof(double) * 4 * (size_t)s->n);
    memcpy(dst->jaw, s->jaw, sizeof(double) * (size_t)s->n);
    if (dst->master_pos && s->master_pos) memcpy(dst->master_pos, s->master_pos, b3);   /* the raw samples */
    if (dst->master_ok && s->master_ok) memcpy(dst->master_ok, s->master_ok, (size_t)s->n);
}
