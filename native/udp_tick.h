/* The haptic tick's side of the UDP receiver (included by udp_rx.c): each master slot's take of
 * its session's newest sample (service/udp_master.py UdpMaster.poll) and its arm's FEEDBACK
 * (service/udp_server.py UdpHub.send_feedback), one call each per master and tick.
 *
 * pf_rx_take_t is a session's tick state (service/udp_session.py Session.take): what earlier
 * ticks took of it, and what this tick takes into the master's own arrays. pf_fb_src_t points at
 * the service's output of the tick (service/tick_io.py TickOutput, bound once) and holds the
 * fields the hub sets once a tick. Times: loop time in s; arrival and tick stamps perf_counter ns. */
#ifndef PF_UDP_TICK_H
#define PF_UDP_TICK_H

typedef struct {
    uint32_t sid;               /* the session (its slot's sessions are told apart by it) */
    int32_t has_state;          /* a sample was taken in this session */
    double timeout_s;           /* silence (loop time) after which the session is dropped */
    int64_t max_age_ns;         /* a sample older than this at the tick is not used (S9) */
    uint64_t seen;              /* samples published when the last new one was taken */
    uint64_t seq, t_client;     /* the taken sample's sequence number and client time (ns) */
    int64_t rx_ns;              /* its kernel arrival */
    double last_rx_t;           /* loop time of the newest sample (NaN: none seen yet) */
    uint64_t tick_rejected;     /* the session's rejections as of the last copy */
    int32_t tick_error;         /* its last error code */
    int32_t clutch, ok;         /* this tick: the pedal; a fresh valid sample */
    uint32_t buttons;
    double grasp;               /* rad */
    int64_t age_ns;             /* this tick's sample age (-1: no sample) */
    double *pos, *quat;         /* the master's position (3, m) and orientation (4, w x y z) */
} pf_rx_take_t;

/* pf_rx_take's answers */
#define PF_TAKE_OK 0            /* taken: ok says whether the master has a valid sample */
#define PF_TAKE_SILENT 1        /* silent past its timeout: the hub drops the session */
#define PF_TAKE_STALE 2         /* the newest sample is older than max_age_ns: not used */

/* Slot k's take at loop time t (s), the tick having started at t_ns (perf_counter ns). */
int pf_rx_take(pf_rx *r, int k, pf_rx_take_t *tk, double t, int64_t t_ns) {
    pf_rx_sample_t c;
    uint64_t n = pf_rx_sample(r, k, tk->sid, &c);
    tk->age_ns = -1;
    if (n == PF_RX_BUSY) {
        n = tk->seen;                         /* being written: the last copy stands this tick */
    } else if (n) {
        tk->tick_rejected = c.rejected;
        tk->tick_error = c.error;
    }
    if (n && n != tk->seen) {
        memcpy(tk->pos, c.pos, sizeof c.pos);
        tk->clutch = (c.flags & PF_F_CLUTCH) != 0;
        tk->buttons = c.buttons;
        if (c.flags & PF_F_ORIENTATION) memcpy(tk->quat, c.quat, sizeof c.quat);
        if (c.flags & PF_F_GRASP) tk->grasp = c.grasp;
        tk->seen = n;
        tk->seq = c.seq;
        tk->t_client = c.t_client;
        tk->rx_ns = c.rx_ns;
        tk->last_rx_t = t;
        tk->has_state = 1;
    } else if (isnan(tk->last_rx_t)) {
        tk->last_rx_t = t;                    /* a new session: its silence counts from this tick */
    }
    if (t - tk->last_rx_t > tk->timeout_s) {
        tk->ok = 0;
        tk->clutch = 0;
        return PF_TAKE_SILENT;
    }
    if (tk->has_state) {
        tk->age_ns = t_ns - tk->rx_ns;
        if (tk->age_ns > tk->max_age_ns) {
            tk->ok = 0;
            return PF_TAKE_STALE;
        }
    }
    tk->ok = tk->has_state;
    return PF_TAKE_OK;
}

typedef struct {
    uint64_t tick, t_tick_ns;   /* the tick's number and start on the deadline grid (ns) */
    uint32_t fixture;           /* FX_* flags of the service (haptics, teleop, fixture mode) */
    uint32_t n;                 /* arms */
    const double *proxy, *robot;   /* (n, 3) world, m */
    const int32_t *contact;     /* (n) each proxy's contact state */
    const int64_t *hold;        /* (n) each arm's hold mask */
    const uint8_t *coupled;     /* (n) */
    const uint8_t *mode;        /* (n) each arm's ROBOT_* mode, set by the hub once a tick */
} pf_fb_src_t;

/* Arm k's FEEDBACK to the session of take tk: force f (3, N, master frame), the rest from src;
 * sent as pf_rx_feedback sends it (1 sent, 0 the send failed, -1 no such session). */
int pf_rx_send_arm(pf_rx *r, int k, const pf_rx_take_t *tk, const pf_fb_src_t *src, const double *f) {
    pf_feedback m;
    if (k < 0 || (uint32_t)k >= src->n) return -1;
    memset(&m, 0, sizeof m);
    m.tick = src->tick;
    m.t_tick_ns = src->t_tick_ns;
    m.echo_seq = tk->seq;
    m.echo_t_client_ns = tk->t_client;
    memcpy(m.force, f, 3 * sizeof(double));
    memcpy(m.proxy, src->proxy + 3 * k, 3 * sizeof(double));
    memcpy(m.robot, src->robot + 3 * k, 3 * sizeof(double));
    m.contact = (uint8_t)src->contact[k];
    m.fixture = (uint8_t)(src->fixture | (src->coupled[k] ? PF_FX_COUPLED : 0));
    m.robot_mode = src->mode[k];
    m.hold = (uint32_t)src->hold[k];
    m.error = (uint16_t)tk->tick_error;
    m.slot = (uint16_t)k;
    m.rejected = (uint32_t)(tk->tick_rejected & 0xFFFFFFFFu);
    return pf_rx_feedback(r, k, tk->sid, &m);
}

#endif
