/* The shared-memory exchange with a robot process (service/robot/hosted.py, hosted_block.py).
 *
 * Channel (hosted_block.Channel): one writer, one reader, a record of `size` doubles in two
 * slots. The writer fills the slot the reader is not pointed at (its counter odd while it
 * writes), stores the CRC-32 of the record's bytes (zlib's: polynomial 0xEDB88320, so Python's
 * zlib.crc32 and this code check each other's writes), makes the counter even and points the
 * reader at the slot. The reader copies the slot it is pointed at and keeps the copy if the
 * slot's counter was even and unchanged around the copy and the CRC matches. Neither side waits.
 *
 * Host (RobotHost): the service's side of every arm, per tick: `pf_host_servo` checks a setpoint
 * (a finite rigid pose inside the arm's workspace) and queues it, `pf_host_step` sends what is
 * queued, reads the child's state record when this arm has taken the last read (the watchdog:
 * heartbeat and readability, each within `timeout_s`), and gives the arm its row if the child
 * answers, the row is finite and the arm is not latched in FAULT. Python acts only on what the
 * returned flags report (a silent child, a non-finite row, a changed text).
 *
 * Built into the tick core (called holding the interpreter lock: microseconds). */
#include <math.h>
#include <stdint.h>
#include <string.h>

int32_t pf_pose_check(const double *T, double tol);   /* tick_quat.h (in tick_core.c) */
void pf_quats_of_matrices(const double *T, int64_t stride, int64_t n, double *q);

/* Slicing-by-8 tables: crc_table[0] is the byte-wise table of zlib's polynomial; crc_table[k][b]
 * is the CRC of byte b followed by k zero bytes, so eight table look-ups fold eight bytes at once
 * (the byte-wise loop's chain of dependent look-ups made a 560-byte state row cost 1.5 us a read,
 * inside the tick). */
static uint32_t crc_table[8][256];
static int crc_ready;

static void crc_init(void) {
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        crc_table[0][i] = c;
    }
    for (uint32_t i = 0; i < 256; i++)
        for (int k = 1; k < 8; k++)
            crc_table[k][i] = (crc_table[k - 1][i] >> 8) ^ crc_table[0][crc_table[k - 1][i] & 0xFFu];
    __atomic_store_n(&crc_ready, 1, __ATOMIC_RELEASE);
}

/* zlib.crc32(bytes) of `n` bytes. */
uint32_t pf_crc32(const void *data, int64_t n) {
    if (!__atomic_load_n(&crc_ready, __ATOMIC_ACQUIRE)) crc_init();
    const uint8_t *p = (const uint8_t *)data;
    uint32_t c = 0xFFFFFFFFu;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    for (; n >= 8; n -= 8, p += 8) {
        uint64_t w;
        memcpy(&w, p, 8);
        const uint32_t lo = (uint32_t)w ^ c, hi = (uint32_t)(w >> 32);
        c = crc_table[7][lo & 0xFFu] ^ crc_table[6][(lo >> 8) & 0xFFu] ^ crc_table[5][(lo >> 16) & 0xFFu] ^
            crc_table[4][lo >> 24] ^ crc_table[3][hi & 0xFFu] ^ crc_table[2][(hi >> 8) & 0xFFu] ^
            crc_table[1][(hi >> 16) & 0xFFu] ^ crc_table[0][hi >> 24];
    }
#endif
    for (; n > 0; n--) c = crc_table[0][(c ^ *p++) & 0xFFu] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

/* A channel's words in the shared block: meta = [counter of slot 0, of slot 1, slot to read,
 * spare], sums = the CRC-32 of each slot, slots = 2 x size doubles. */
typedef struct {
    int64_t *meta;
    int64_t *sums;
    double *slots;
    int64_t size;
} pf_channel;

#define BARRIER() __atomic_thread_fence(__ATOMIC_SEQ_CST)

void pf_chan_write(const pf_channel *c, const double *rec) {
    volatile int64_t *meta = c->meta;
    const int64_t w = 1 - meta[2];
    meta[w] = meta[w] + 1;                                 /* odd: being written */
    BARRIER();
    memcpy(c->slots + w * c->size, rec, (size_t)c->size * sizeof(double));
    ((volatile int64_t *)c->sums)[w] = (int64_t)pf_crc32(rec, c->size * (int64_t)sizeof(double));
    BARRIER();
    meta[w] = meta[w] + 1;                                 /* even: whole */
    BARRIER();
    meta[2] = w;
}

/* 1 if a whole record was copied into `out` within `tries` attempts, else 0 (lapped). */
int32_t pf_chan_read(const pf_channel *c, double *out, int32_t tries) {
    volatile const int64_t *meta = c->meta;
    for (int32_t t = 0; t < tries; t++) {
        const int64_t i = meta[2];
        if (i != 0 && i != 1) continue;
        BARRIER();
        const int64_t s1 = meta[i];
        if (s1 & 1) continue;
        BARRIER();
        memcpy(out, c->slots + i * c->size, (size_t)c->size * sizeof(double));
        BARRIER();
        if (meta[i] == s1 && (int64_t)pf_crc32(out, c->size * (int64_t)sizeof(double)) ==
                                 ((volatile const int64_t *)c->sums)[i])
            return 1;
    }
    return 0;
}

/* The indices of one arm's fields in a state row (hosted_block.state_dtype) and a command row
 * (hosted_block.COMMAND), as flat doubles. */
typedef struct {
    int32_t t, mode, rejected, ignored, servo_seq, mode_seq, fault_ver, error_ver;
    int32_t q, dq, tau, q_d, T_meas, T_d, jaw, jaw_known, dof;
    int32_t c_servo_seq, c_mode_seq, c_pose, c_jaw_seq, c_jaw;
} pf_host_layout;

typedef struct {
    int64_t n, S, C;            /* arms; doubles per state row, per command row */
    pf_channel state, cmd;      /* child -> service, service -> child */
    const int64_t *ticks;       /* the child's heartbeat (periods stepped) */
    double *buf;                /* (n, S) the state record last read */
    double *taken;              /* (n, S) each arm's row as it last took one */
    double *cmds;               /* (n, C) the commands written so far (this side's copy) */
    double *T_d;                /* (n, 16) each arm's setpoint (world, row-major) */
    double *q_d;                /* (n, dof) each arm's joint setpoint */
    double *mode;               /* (n) each arm's mode (RobotMode) */
    double *versions;           /* (n, 2) the fault and error text versions last seen */
    double *rejected_seen;      /* (n) the child's rejections servo_cp has reported */
    double *ws;                 /* (n, 6) each arm's workspace box (min xyz, max xyz) */
    int64_t *took;              /* (n) the read each arm took last */
    uint8_t *has_ws;            /* (n) whether the arm has a workspace */
    uint8_t *latched;           /* (n) the arm is latched in FAULT (Python sets it) */
    uint8_t *finite;            /* (n) the arm's row of the last read was finite */
    uint8_t *fresh;             /* (n) the arm took a row Python has not adopted yet */
    pf_host_layout L;
    double timeout_s, rigid_tol, enabled_mode;
    double ticks_at, read_at, silent, unread;   /* monotonic s; s */
    int64_t ticks_last, reads, nonfinite, texts; /* nonfinite, texts: arm bitmasks of the last read */
    int32_t staged, got, alive;
} pf_host;

/* pf_host_step's and pf_host_sync's flags */
#define PF_HOST_LOST 1          /* the child is silent or its record unreadable (alive == 0) */
#define PF_HOST_NONFINITE 2     /* an arm's row holds a NaN or an infinity (nonfinite) */
#define PF_HOST_TEXTS 4         /* an arm's fault or error text changed (texts) */
#define PF_HOST_REFUSED 8       /* pf_host_command: an arm's setpoint was not queued (a code > 0) */

/* pf_host_servo's codes */
#define PF_SERVO_QUEUED 0
#define PF_SERVO_BAD_POSE 1     /* not a finite rigid transform */
#define PF_SERVO_WORKSPACE 2    /* outside the arm's workspace */
#define PF_SERVO_IGNORED 3      /* the arm is latched or not ENABLED */
#define PF_SERVO_REJECTED 4     /* the child rejected the previous setpoint (not yet reported) */

void pf_host_publish(pf_host *h) {
    if (!h->staged) return;
    pf_chan_write(&h->cmd, h->cmds);
    h->staged = 0;
}

/* Arm b's setpoint T (4x4 world, row-major): checked, then queued for the next publish. */
int32_t pf_host_servo(pf_host *h, int64_t b, const double *T) {
    const double *row = h->taken + b * h->S;
    if (row[h->L.rejected] > h->rejected_seen[b]) {
        h->rejected_seen[b] = row[h->L.rejected];
        return PF_SERVO_REJECTED;
    }
    if (pf_pose_check(T, h->rigid_tol)) return PF_SERVO_BAD_POSE;
    if (h->has_ws[b]) {
        const double *w = h->ws + 6 * b;
        if (!(w[0] <= T[3] && T[3] <= w[3] && w[1] <= T[7] && T[7] <= w[4] && w[2] <= T[11] && T[11] <= w[5]))
            return PF_SERVO_WORKSPACE;
    }
    if (h->latched[b] || h->mode[b] != h->enabled_mode) return PF_SERVO_IGNORED;
    double *c = h->cmds + b * h->C;
    memcpy(c + h->L.c_pose, T, 16 * sizeof(double));
    c[h->L.c_servo_seq] += 1.0;
    memcpy(h->T_d + 16 * b, T, 16 * sizeof(double));
    h->staged = 1;
    return PF_SERVO_QUEUED;
}

static int row_finite(const double *r, int64_t S) {
    double s = 0.0;
    for (int64_t i = 0; i < S; i++) s += r[i] * 0.0;       /* NaN or inf anywhere: NaN */
    return s == 0.0;
}

/* Read the state record (after the watchdog); returns the flags of this read. */
static int32_t host_read(pf_host *h, double now) {
    h->reads += 1;
    const int64_t ticks = *(volatile const int64_t *)h->ticks;
    if (ticks != h->ticks_last) {
        h->ticks_last = ticks;
        h->ticks_at = now;
    }
    h->got = pf_chan_read(&h->state, h->buf, 8);
    if (h->got) h->read_at = now;
    h->silent = now - h->ticks_at;
    h->unread = now - h->read_at;
    h->alive = h->silent <= h->timeout_s && h->unread <= h->timeout_s;
    int32_t flags = h->alive ? 0 : PF_HOST_LOST;
    h->nonfinite = 0;
    h->texts = 0;
    if (!h->got) return flags;
    const pf_host_layout *L = &h->L;
    for (int64_t b = 0; b < h->n; b++) {
        const double *r = h->buf + b * h->S;
        h->finite[b] = (uint8_t)row_finite(r, h->S);
        if (!h->finite[b]) {
            h->nonfinite |= (int64_t)1 << b;
            flags |= PF_HOST_NONFINITE;
            continue;
        }
        double *v = h->versions + 2 * b;
        if (r[L->fault_ver] != v[0] || r[L->error_ver] != v[1]) {
            v[0] = r[L->fault_ver];
            v[1] = r[L->error_ver];
            h->texts |= (int64_t)1 << b;
            flags |= PF_HOST_TEXTS;
        }
    }
    return flags;
}

/* Arm b takes its row of the last read where the read succeeded, the child answers, the row is
 * finite and the arm is not latched: the measured state, the child's mode once it has applied
 * every mode command sent, the child's setpoint once it has applied every setpoint sent. */
static void host_give(pf_host *h, int64_t b) {
    h->took[b] = h->reads;
    if (!(h->got && h->alive && h->finite[b] && !h->latched[b])) return;
    const pf_host_layout *L = &h->L;
    const double *r = h->buf + b * h->S;
    const double *c = h->cmds + b * h->C;
    memcpy(h->taken + b * h->S, r, (size_t)h->S * sizeof(double));
    if (r[L->mode_seq] >= c[L->c_mode_seq]) h->mode[b] = r[L->mode];
    if (r[L->servo_seq] >= c[L->c_servo_seq]) {
        memcpy(h->T_d + 16 * b, r + L->T_d, 16 * sizeof(double));
        memcpy(h->q_d + L->dof * b, r + L->q_d, (size_t)L->dof * sizeof(double));
    }
    h->fresh[b] = 1;
}

/* Arm b's step at monotonic time `now` (s): send what is queued, read the record again if this
 * arm took the last read, give the arm its row. Returns the flags of a read made now (0: none,
 * or nothing to report). */
int32_t pf_host_step(pf_host *h, int64_t b, double now) {
    pf_host_publish(h);
    int32_t flags = 0;
    if (h->took[b] == h->reads) flags = host_read(h, now);
    host_give(h, b);
    return flags;
}

/* Every arm's commands of a tick at once (service/devices.py Devices.command_robots, when every
 * robot is an arm of this host, arm b on row b): each coupled arm's setpoint T4[b] (4x4 world)
 * checked and queued (codes[b]: pf_host_servo's code; -1: not coupled, nothing sent), then every
 * arm stepped, in index order. Returns the flags of the read made, and PF_HOST_REFUSED where an
 * arm's code is > 0. */
int32_t pf_host_command(pf_host *h, const double *T4, const uint8_t *coupled, int32_t *codes, double now) {
    int32_t flags = 0;
    for (int64_t b = 0; b < h->n; b++) {
        codes[b] = coupled[b] ? pf_host_servo(h, b, T4 + 16 * b) : -1;
        if (codes[b] > 0) flags |= PF_HOST_REFUSED;
    }
    for (int64_t b = 0; b < h->n; b++) flags |= pf_host_step(h, b, now);
    return flags;
}

/* Read the record and give every arm its row (the host's start, a restart). */
int32_t pf_host_sync(pf_host *h, double now) {
    const int32_t flags = host_read(h, now);
    for (int64_t b = 0; b < h->n; b++) host_give(h, b);
    return flags;
}

/* What the tick reads of every arm (service/devices.py Devices.read_robots, when every robot is
 * an arm of this host, arm b on row b), from the rows the arms took: measured poses T4 (n, 16,
 * world, row-major), tips pos (n, 3), orientations quat (n, 4, w x y z), fault (n: latched or
 * FAULT), present (n: 1), jaw (n, rad): an arm with a jaw (jawed[b]) its measured one (NaN
 * while unknown), an arm without one ideal_jaw[b] (its command). `fault_mode`: RobotMode.FAULT. */
void pf_host_read_poses(const pf_host *h, double fault_mode, double *T4, double *pos, double *quat, uint8_t *fault,
                        uint8_t *present, double *jaw, const uint8_t *jawed, const double *ideal_jaw) {
    const pf_host_layout *L = &h->L;
    for (int64_t b = 0; b < h->n; b++) {
        const double *r = h->taken + b * h->S;
        double *t = T4 + 16 * b;
        memcpy(t, r + L->T_meas, 16 * sizeof(double));
        pos[3 * b] = t[3];
        pos[3 * b + 1] = t[7];
        pos[3 * b + 2] = t[11];
        fault[b] = (uint8_t)(h->latched[b] || h->mode[b] == fault_mode);
        present[b] = 1;
        jaw[b] = !jawed[b] ? ideal_jaw[b] : r[L->jaw_known] == 1.0 ? r[L->jaw] : NAN;
    }
    pf_quats_of_matrices(T4, 4, h->n, quat);
}
