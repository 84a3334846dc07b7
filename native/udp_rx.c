/* pointfence's UDP receiver: the STATE path of the hub (service/udp_server.py) in a thread of
 * its own that never takes Python's interpreter lock.
 *
 * A device's STATE must reach the haptic tick within its session's timeout (50 ms) however busy
 * the service's interpreter is. A receiver in Python waited for the interpreter lock between
 * datagrams: during a flood, an operator action or a control request the samples the ticks used
 * were tens of milliseconds old and sessions lapsed (arms held, S9). Here a C thread reads the
 * socket (recvmmsg, each datagram with its kernel arrival time) and takes every STATE that
 * names a live session from that session's own address: window, tag (HMAC-SHA256 truncated to
 * 16 bytes), values, then the session's latest sample (a seqlock the tick reads without
 * waiting). Within one read batch each session's STATEs are taken newest first; the older ones
 * are checked after it and counted as superseded, never used (as the Python drain did). Before
 * any of that, every source address has a token bucket: a flood is dropped before its header is
 * read. Everything else (handshakes, BYEs, datagrams from elsewhere, malformed ones) is queued
 * for the hub's Python thread, which answers and counts them; the queue is bounded (a full
 * queue drops the newest, counted). The tick also sends each session's FEEDBACK through here
 * (pf_rx_feedback: the session's key and address, copied without waiting).
 *
 * The checks of one session's STATE are in udp_rx_session.h. Addresses are IPv4, host byte
 * order. Times are CLOCK_MONOTONIC ns (Python's perf_counter_ns).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <poll.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <netinet/in.h>
#include <time.h>
#include <unistd.h>

#include "pointfence_client.h"
#include "udp_rx_session.h"

#define BATCH 256                   /* datagrams per recvmmsg: more than the receive buffer holds */
#define NOT_MINE (-1)
#define PF_RX_BUSY UINT64_MAX       /* pf_rx_sample: the sample was being written each time */
#define PF_RX_TRIES 16              /* seqlock reads the tick tries before it gives up */

/* what the tick copies (service/udp_native.py mirrors it) */
typedef struct {
    uint64_t n, seq, t_client;
    int64_t rx_ns;
    double pos[3], quat[4], grasp;
    uint32_t flags, buttons;
    uint64_t rejected;
    int32_t error, pad;
} pf_rx_sample_t;

/* a source's token bucket (udp_ratelimit.SourceLimiter's, in C) */
typedef struct {
    uint32_t ip, port, used, pad;
    int64_t last;                   /* ns; 0: not yet used */
    double tokens;
} bucket_t;

#define NBUCKETS 2048               /* sources with a bucket of their own at most */
#define PROBE 16

typedef struct {
    uint32_t len, ip, port, pad;
    int64_t rx_ns;
    uint8_t data[PF_MAX_DATAGRAM];
} entry_t;

typedef struct {
    int fd, nslots, cap;
    slot_t *slots;
    pthread_mutex_t mu;             /* slots' sessions and windows; the queue */
    pthread_cond_t cv;
    entry_t *q;
    int head, count;
    volatile int stop;
    int running, tid;
    pthread_t th;
    uint64_t received, accepted, superseded, kernel_dropped, queue_dropped, counts[N_CODES];
    /* per-source rate limit, before any header is read */
    bucket_t buckets[NBUCKETS], overflow;
    double rate, burst;
    int64_t idle_ns;
    uint64_t rate_limited, overflowed, sources;
    /* one read batch */
    struct mmsghdr msgs[BATCH];
    struct iovec iov[BATCH];
    struct sockaddr_in from[BATCH];
    uint8_t bufs[BATCH][PF_MAX_DATAGRAM];
    uint8_t ctl[BATCH][64];
    int64_t arrival[BATCH];         /* perf_counter ns */
} pf_rx;

static int64_t clock_ns(clockid_t c) {
    struct timespec ts;
    clock_gettime(c, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* --- sessions ------------------------------------------------------------------------------- */

/* the source ``ip``:``port``'s bucket: its own (a new one takes a free place, or one idle for
 * idle_ns, among PROBE places), or the overflow bucket that every further new source shares
 * (a flood from many spoofed addresses competes only with itself). */
static bucket_t *bucket(pf_rx *r, uint32_t ip, uint32_t port, int64_t now) {
    uint32_t h = ip * 2654435761u ^ port * 40503u;
    bucket_t *spare = NULL;
    int i;
    h ^= h >> 15;
    for (i = 0; i < PROBE; i++) {
        bucket_t *b = &r->buckets[(h + (uint32_t)i) & (NBUCKETS - 1)];
        if (b->used && b->ip == ip && b->port == port) return b;
        if (spare == NULL && (!b->used || now - b->last > r->idle_ns)) spare = b;
    }
    if (spare == NULL) { r->overflowed += 1; return &r->overflow; }
    if (!spare->used) r->sources += 1;
    spare->used = 1; spare->ip = ip; spare->port = port; spare->last = 0; spare->tokens = r->burst;
    return spare;
}

/* Take a token for one datagram from ip:port at ``now`` (ns); 0: drop it. */
static int allow(pf_rx *r, uint32_t ip, uint32_t port, int64_t now) {
    bucket_t *b = bucket(r, ip, port, now);
    double t = b->last == 0 ? b->tokens : b->tokens + (double)(now - b->last) * 1e-9 * r->rate;
    if (t > r->burst) t = r->burst;
    b->last = now;
    if (t < 1.0) { b->tokens = t; r->rate_limited += 1; return 0; }
    b->tokens = t - 1.0;
    return 1;
}

/* a source may send ``rate`` datagrams/s on average, ``burst`` at once; a bucket idle for
 * ``idle_s`` may go to a new source */
void pf_rx_limits(pf_rx *r, double rate, double burst, double idle_s) {
    pthread_mutex_lock(&r->mu);
    r->rate = rate; r->burst = burst; r->idle_ns = (int64_t)(idle_s * 1e9);
    r->overflow.tokens = burst; r->overflow.last = 0;
    pthread_mutex_unlock(&r->mu);
}

pf_rx *pf_rx_new(int fd, int nslots, int cap) {
    pf_rx *r;
    int i;
    if (nslots < 1 || cap < 1) return NULL;
    r = (pf_rx *)calloc(1, sizeof *r);
    if (!r) return NULL;
    r->slots = (slot_t *)calloc((size_t)nslots, sizeof(slot_t));
    r->q = (entry_t *)calloc((size_t)cap, sizeof(entry_t));
    if (!r->slots || !r->q) { free(r->slots); free(r->q); free(r); return NULL; }
    r->fd = fd; r->nslots = nslots; r->cap = cap;
    r->rate = 4000.0; r->burst = 400.0; r->idle_ns = 10000000000LL;
    r->overflow.tokens = r->burst;
    pthread_mutex_init(&r->mu, NULL);
    pthread_cond_init(&r->cv, NULL);
    for (i = 0; i < BATCH; i++) {
        r->iov[i].iov_base = r->bufs[i];
        r->iov[i].iov_len = PF_MAX_DATAGRAM;
        r->msgs[i].msg_hdr.msg_iov = &r->iov[i];
        r->msgs[i].msg_hdr.msg_iovlen = 1;
    }
    return r;
}

/* slot ``k`` now holds session ``sid`` of device ``dev`` from ip:port (host order); key: the
 * session key; ws: workspace min x y z, max x y z (m); max_force: N. Its window, sample, counts
 * and sequence numbers start anew. */
void pf_rx_open(pf_rx *r, int k, uint32_t sid, uint32_t dev, const uint8_t *key, int keylen, uint32_t ip,
                uint32_t port, const double *ws, double max_force) {
    uint8_t kb[64], pad[64];
    slot_t *s;
    int i;
    if (k < 0 || k >= r->nslots || keylen < 0 || keylen > 64) return;
    memset(kb, 0, sizeof kb);
    memcpy(kb, key, (size_t)keylen);
    pthread_mutex_lock(&r->mu);
    s = &r->slots[k];
    __atomic_store_n(&s->sl, s->sl + 1, __ATOMIC_RELEASE);     /* odd: the tick keeps its last copy */
    __atomic_store_n(&s->live, 0, __ATOMIC_RELEASE);
    s->sid = sid; s->dev = dev; s->ip = ip; s->port = port;
    memcpy(s->key, kb, sizeof s->key); s->keylen = keylen;
    s->max_force = max_force; s->tx = 0;
    for (i = 0; i < 64; i++) pad[i] = (uint8_t)(kb[i] ^ 0x36);
    pf_sha256_init(&s->ictx); pf_sha256_update(&s->ictx, pad, 64);
    for (i = 0; i < 64; i++) pad[i] = (uint8_t)(kb[i] ^ 0x5c);
    pf_sha256_init(&s->octx); pf_sha256_update(&s->octx, pad, 64);
    for (i = 0; i < 3; i++) { s->ws_lo[i] = ws[i]; s->ws_hi[i] = ws[3 + i]; }
    s->win.top = s->win.bits = 0;
    s->accepted = s->rejected = s->superseded = 0;
    s->error = PF_OK; s->proven = 0;
    s->n = 0;
    __atomic_store_n(&s->live, 1, __ATOMIC_RELEASE);
    __atomic_store_n(&s->sl, s->sl + 1, __ATOMIC_RELEASE);
    pthread_mutex_unlock(&r->mu);
    memset(kb, 0, sizeof kb);
    memset(pad, 0, sizeof pad);
}

void pf_rx_close(pf_rx *r, int k, uint32_t sid) {
    if (k < 0 || k >= r->nslots) return;
    pthread_mutex_lock(&r->mu);
    if (r->slots[k].sid == sid) __atomic_store_n(&r->slots[k].live, 0, __ATOMIC_RELEASE);
    pthread_mutex_unlock(&r->mu);
}

static slot_t *session_of(pf_rx *r, uint32_t sid, uint32_t dev, uint32_t ip, uint32_t port) {
    int k;
    for (k = 0; k < r->nslots; k++) {
        slot_t *s = &r->slots[k];
        if (s->live && s->sid == sid && s->dev == dev && s->ip == ip && s->port == port) return s;
    }
    return NULL;
}

static slot_t *held(pf_rx *r, int k, uint32_t sid) {
    if (k < 0 || k >= r->nslots || !r->slots[k].live || r->slots[k].sid != sid) return NULL;
    return &r->slots[k];
}

/* The hub's BYE: check (commit 0) or record (commit 1) ``seq`` in the window of the session
 * ``sid`` on slot ``k``; returns an E_* code (PF_E_NO_SESSION if the slot holds another). */
int pf_rx_window(pf_rx *r, int k, uint32_t sid, uint64_t seq, int commit) {
    slot_t *s;
    int code;
    pthread_mutex_lock(&r->mu);
    s = held(r, k, sid);
    code = s == NULL ? PF_E_NO_SESSION : pf_window_check(&s->win, seq);
    if (code == PF_OK && commit) pf_window_commit(&s->win, seq);
    pthread_mutex_unlock(&r->mu);
    return code;
}

static void reject(pf_rx *r, slot_t *s, int code) {
    r->counts[code] += 1;
    if (s != NULL) { s->rejected += 1; s->error = code; }
}

/* A datagram the hub's Python refused for a live session (a BYE's tag, say): counted against it. */
void pf_rx_note(pf_rx *r, int k, uint32_t sid, int code) {
    slot_t *s;
    pthread_mutex_lock(&r->mu);
    s = held(r, k, sid);
    if (s != NULL) { s->rejected += 1; s->error = code; }
    pthread_mutex_unlock(&r->mu);
}

/* Check one STATE of ``s`` (the mutex held). newest: it may become the sample (else it is older
 * than one this batch accepted: checked, recorded where the window still holds it, never used). */
static int take(pf_rx *r, slot_t *s, const uint8_t *d, int64_t rx_ns, int newest) {
    uint64_t seq = rd64(d + 12);
    int code, inside = 1;
    if (newest) {
        code = pf_window_check(&s->win, seq);
        if (code == PF_OK && seq <= s->win.top) code = PF_E_STALE;      /* older than the newest sample */
    } else {
        inside = s->win.top - seq < PF_WINDOW;
        code = inside ? pf_window_check(&s->win, seq) : PF_OK;
    }
    if (code == PF_OK && !tag_ok(s, d)) code = PF_E_AUTH;
    if (code == PF_OK) code = values_ok(s, d);
    if (code != PF_OK) { reject(r, s, code); return code; }
    if (!newest) {
        if (inside) pf_window_commit(&s->win, seq);
        s->superseded += 1; r->superseded += 1;
        return PF_OK;
    }
    pf_window_commit(&s->win, seq);
    publish(s, d, rx_ns);
    s->proven = 1;
    s->accepted += 1; r->accepted += 1;
    return PF_OK;
}

/* Whether ``d`` is a STATE for the fast path: a well-formed header naming a live session from
 * its own address. (Python counts everything else, with its reasons.) */
static slot_t *candidate(pf_rx *r, const uint8_t *d, int n, uint32_t ip, uint32_t port) {
    if (n != PF_STATE_SIZE || d[0] != 'P' || d[1] != 'F' || d[2] != PF_PROTOCOL_VERSION || d[3] != PF_STATE ||
        rd32(d + 20) != 0)
        return NULL;
    return session_of(r, rd32(d + 8), rd32(d + 4), ip, port);
}

/* The hub's handle() of one STATE: the fast path's code, or NOT_MINE. */
int pf_rx_feed(pf_rx *r, const uint8_t *d, int n, uint32_t ip, uint32_t port, int64_t rx_ns) {
    slot_t *s;
    int code = NOT_MINE;
    pthread_mutex_lock(&r->mu);
    s = candidate(r, d, n, ip, port);
    if (s != NULL) code = take(r, s, d, rx_ns, 1);
    pthread_mutex_unlock(&r->mu);
    return code;
}

/* --- the queue for Python --------------------------------------------------------------------- */

static void enqueue(pf_rx *r, const uint8_t *d, int n, uint32_t ip, uint32_t port, int64_t rx_ns) {
    entry_t *e;
    if (r->count == r->cap) { r->queue_dropped += 1; return; }
    e = &r->q[(r->head + r->count) % r->cap];
    e->len = (uint32_t)n; e->ip = ip; e->port = port; e->rx_ns = rx_ns;
    memcpy(e->data, d, (size_t)n);
    r->count += 1;
}

/* The next datagram for Python: its length (0: none within timeout_ms; -1: stopped), address and
 * arrival. timeout_ms 0 never waits (call it holding the interpreter lock). */
int pf_rx_next(pf_rx *r, int timeout_ms, uint8_t *buf, int cap, uint32_t *ip, uint32_t *port, int64_t *rx_ns) {
    entry_t *e;
    int n;
    pthread_mutex_lock(&r->mu);
    if (r->count == 0 && timeout_ms > 0 && !r->stop) {
        struct timespec until;
        int64_t t = clock_ns(CLOCK_REALTIME) + (int64_t)timeout_ms * 1000000LL;
        until.tv_sec = (time_t)(t / 1000000000LL);
        until.tv_nsec = (long)(t % 1000000000LL);
        while (r->count == 0 && !r->stop)
            if (pthread_cond_timedwait(&r->cv, &r->mu, &until) == ETIMEDOUT) break;
    }
    if (r->count == 0) { n = r->stop ? -1 : 0; pthread_mutex_unlock(&r->mu); return n; }
    e = &r->q[r->head];
    n = (int)e->len < cap ? (int)e->len : cap;
    memcpy(buf, e->data, (size_t)n);
    *ip = e->ip; *port = e->port; *rx_ns = e->rx_ns;
    r->head = (r->head + 1) % r->cap;
    r->count -= 1;
    pthread_mutex_unlock(&r->mu);
    return n;
}

/* --- reading the socket --------------------------------------------------------------------- */

/* One recvmmsg batch, applied; returns the datagrams read (0: none waiting, -1: socket error). */
static int read_batch(pf_rx *r) {
    int got, i, j, queued = 0;
    int64_t off, now;
    slot_t *who[BATCH];
    for (i = 0; i < BATCH; i++) {
        struct msghdr *h = &r->msgs[i].msg_hdr;
        h->msg_name = &r->from[i]; h->msg_namelen = sizeof r->from[i];
        h->msg_control = r->ctl[i]; h->msg_controllen = sizeof r->ctl[i];
        h->msg_flags = 0;
    }
    got = recvmmsg(r->fd, r->msgs, BATCH, MSG_DONTWAIT, NULL);
    if (got < 0) return (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR || errno == ECONNREFUSED) ? 0 : -1;
    now = clock_ns(CLOCK_MONOTONIC);
    off = clock_ns(CLOCK_REALTIME) - now;
    pthread_mutex_lock(&r->mu);
    r->received += (uint64_t)got;
    for (i = 0; i < got; i++) {
        struct msghdr *h = &r->msgs[i].msg_hdr;
        struct cmsghdr *c;
        int64_t t = 0;
        uint32_t ip = ntohl(r->from[i].sin_addr.s_addr), port = ntohs(r->from[i].sin_port);
        for (c = CMSG_FIRSTHDR(h); c != NULL; c = CMSG_NXTHDR(h, c)) {
            if (c->cmsg_level != SOL_SOCKET) continue;
            if (c->cmsg_type == SCM_TIMESTAMPNS && c->cmsg_len >= CMSG_LEN(sizeof(struct timespec))) {
                struct timespec ts;
                memcpy(&ts, CMSG_DATA(c), sizeof ts);
                t = (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec - off;
            } else if (c->cmsg_type == SO_RXQ_OVFL && c->cmsg_len >= CMSG_LEN(4)) {
                uint32_t d;
                memcpy(&d, CMSG_DATA(c), 4);
                r->kernel_dropped = d;
            }
        }
        r->arrival[i] = (0 < t && t < now) ? t : now;
        if (!allow(r, ip, port, now)) { who[i] = NULL; continue; }
        who[i] = candidate(r, r->bufs[i], (int)r->msgs[i].msg_len, ip, port);
        if (who[i] != NULL) {      /* replayed, stale or older than the sample before this read: no MAC */
            uint64_t seq = rd64(r->bufs[i] + 12);
            int code = pf_window_check(&who[i]->win, seq);
            if (code == PF_OK && seq <= who[i]->win.top) code = PF_E_STALE;
            if (code != PF_OK) { reject(r, who[i], code); who[i] = NULL; }
            continue;
        }
        enqueue(r, r->bufs[i], (int)r->msgs[i].msg_len, ip, port, r->arrival[i]);
        queued = 1;
    }
    /* each session's STATEs of this batch, newest first: the first accepted is the sample */
    for (i = 0; i < got; i++) {
        slot_t *s = who[i];
        int taken = 0;
        if (s == NULL) continue;
        for (;;) {
            int best = -1;
            uint64_t bseq = 0;
            for (j = i; j < got; j++)
                if (who[j] == s && (best < 0 || rd64(r->bufs[j] + 12) > bseq)) { best = j; bseq = rd64(r->bufs[j] + 12); }
            if (best < 0) break;
            who[best] = NULL;
            if (take(r, s, r->bufs[best], r->arrival[best], !taken) == PF_OK) taken = 1;
        }
    }
    if (queued) pthread_cond_signal(&r->cv);
    pthread_mutex_unlock(&r->mu);
    return got;
}

/* Read what waits, without blocking (the hub's pump() where no thread runs): until the socket
 * is empty, ``max`` datagrams were read or the queue for Python is full; returns how many. */
int pf_rx_poll(pf_rx *r, int max) {
    int total = 0, got;
    while (total < max) {
        pthread_mutex_lock(&r->mu);
        got = r->count;
        pthread_mutex_unlock(&r->mu);
        if (got > r->cap - BATCH) break;
        got = read_batch(r);
        if (got <= 0) break;
        total += got;
    }
    return total;
}

static void *run(void *arg) {
    pf_rx *r = (pf_rx *)arg;
    struct pollfd p;
    r->tid = (int)syscall(SYS_gettid);
    p.fd = r->fd; p.events = POLLIN;
    while (!r->stop) {
        p.revents = 0;
        if (poll(&p, 1, 20) < 0 && errno != EINTR) break;
        if (p.revents & (POLLERR | POLLNVAL)) {
            if (read_batch(r) < 0 && (p.revents & POLLNVAL)) break;
            continue;
        }
        if (p.revents & POLLIN)
            while (!r->stop && read_batch(r) == BATCH) {}
    }
    pthread_mutex_lock(&r->mu);
    r->stop = 1;
    pthread_cond_broadcast(&r->cv);
    pthread_mutex_unlock(&r->mu);
    return NULL;
}

/* Start the receiver thread; returns its OS thread id (for its scheduling), or -1. */
int pf_rx_start(pf_rx *r) {
    int i;
    if (r->running) return r->tid;
    r->stop = 0;
    if (pthread_create(&r->th, NULL, run, r) != 0) return -1;
    r->running = 1;
    for (i = 0; i < 1000 && __atomic_load_n(&r->tid, __ATOMIC_ACQUIRE) == 0; i++) usleep(100);
    return r->tid;
}

/* Stop the thread (within its 20 ms poll) and wake a waiting pf_rx_next. */
void pf_rx_stop(pf_rx *r) {
    pthread_mutex_lock(&r->mu);
    r->stop = 1;
    pthread_cond_broadcast(&r->cv);
    pthread_mutex_unlock(&r->mu);
    if (r->running) { pthread_join(r->th, NULL); r->running = 0; }
}

void pf_rx_free(pf_rx *r) {
    if (r == NULL) return;
    pf_rx_stop(r);
    pthread_mutex_destroy(&r->mu);
    pthread_cond_destroy(&r->cv);
    memset(r->slots, 0, (size_t)r->nslots * sizeof(slot_t));
    free(r->slots); free(r->q); free(r);
}

/* --- what the tick and the status read ---------------------------------------------------------- */

/* The tick: copy slot k's latest sample if it still holds session ``sid``; returns the samples
 * published so far (0: none, or another session), or PF_RX_BUSY: the sample was being written
 * each time it looked (keep the last copy). It never waits for the writer: the receiver may be
 * preempted mid-write by the very thread that reads. */
uint64_t pf_rx_sample(pf_rx *r, int k, uint32_t sid, pf_rx_sample_t *out) {
    slot_t *s;
    uint64_t a, b;
    int i;
    if (k < 0 || k >= r->nslots) return 0;
    s = &r->slots[k];
    for (i = 0; i < PF_RX_TRIES; i++) {
        a = __atomic_load_n(&s->sl, __ATOMIC_ACQUIRE);
        if (a & 1u) continue;
        if (!__atomic_load_n(&s->live, __ATOMIC_ACQUIRE) || s->sid != sid) {
            b = __atomic_load_n(&s->sl, __ATOMIC_ACQUIRE);
            if (a != b) continue;
            out->n = 0;
            return 0;
        }
        out->n = s->n; out->seq = s->seq; out->t_client = s->t_client; out->rx_ns = s->rx_ns;
        memcpy(out->pos, s->pos, sizeof out->pos);
        memcpy(out->quat, s->quat, sizeof out->quat);
        out->grasp = s->grasp; out->flags = s->flags; out->buttons = s->buttons;
        out->rejected = s->rejected; out->error = s->error;
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        b = __atomic_load_n(&s->sl, __ATOMIC_RELAXED);
        if (a == b) return out->n;
    }
    return PF_RX_BUSY;
}

/* The session's next outgoing sequence number (its FEEDBACKs and the service's BYE), or 0 if
 * slot k holds another session. */
uint64_t pf_rx_next_tx(pf_rx *r, int k, uint32_t sid) {
    slot_t *s;
    uint64_t seq = 0;
    pthread_mutex_lock(&r->mu);
    s = held(r, k, sid);
    if (s != NULL) seq = __atomic_add_fetch(&s->tx, 1, __ATOMIC_RELAXED);
    pthread_mutex_unlock(&r->mu);
    return seq;
}

/* The tick: FEEDBACK ``m`` to session ``sid`` on slot k, its force saturated at the session's
 * limit (zero if not finite), stamped (t_sent_ns, perf_counter ns), tagged and sent without
 * blocking. Never waits for the receiver (the slot's key and address are copied under its
 * seqlock). Returns 1 sent, 0 the send failed, -1 no such session (or it was being replaced). */
int pf_rx_feedback(pf_rx *r, int k, uint32_t sid, pf_feedback *m) {
    slot_t *s;
    uint8_t key[PF_KEY_MAX], out[PF_FEEDBACK_SIZE];
    uint32_t dev = 0, ip = 0, port = 0, live = 0, ssid = 0;
    int32_t keylen = 0;
    double mf = 0.0, n2;
    uint64_t a, b;
    struct sockaddr_in to;
    size_t n;
    int i, got = 0;
    if (k < 0 || k >= r->nslots) return -1;
    s = &r->slots[k];
    for (i = 0; i < PF_RX_TRIES && !got; i++) {
        a = __atomic_load_n(&s->sl, __ATOMIC_ACQUIRE);
        if (a & 1u) continue;
        live = s->live; ssid = s->sid; dev = s->dev; ip = s->ip; port = s->port;
        keylen = s->keylen; mf = s->max_force;
        memcpy(key, s->key, sizeof key);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        b = __atomic_load_n(&s->sl, __ATOMIC_RELAXED);
        got = a == b;
    }
    if (!got || !live || ssid != sid) return -1;
    if (!(isfinite(m->force[0]) && isfinite(m->force[1]) && isfinite(m->force[2])))
        m->force[0] = m->force[1] = m->force[2] = 0.0;
    n2 = m->force[0] * m->force[0] + m->force[1] * m->force[1] + m->force[2] * m->force[2];
    if (n2 > mf * mf) {
        double c = mf / sqrt(n2);
        for (i = 0; i < 3; i++) m->force[i] *= c;
    }
    m->t_sent_ns = (uint64_t)clock_ns(CLOCK_MONOTONIC);
    n = pf_encode_feedback(out, sizeof out, key, (size_t)keylen, dev, sid, __atomic_add_fetch(&s->tx, 1, __ATOMIC_RELAXED), m);
    memset(key, 0, sizeof key);
    if (n == 0) return 0;
    memset(&to, 0, sizeof to);
    to.sin_family = AF_INET; to.sin_addr.s_addr = htonl(ip); to.sin_port = htons((uint16_t)port);
    return sendto(r->fd, out, n, MSG_DONTWAIT | MSG_NOSIGNAL, (struct sockaddr *)&to, sizeof to) == (ssize_t)n ? 1 : 0;
}

/* slot k's session counts: accepted, rejected, superseded, error, proven (all 0 if it holds another) */
void pf_rx_session_stats(pf_rx *r, int k, uint32_t sid, uint64_t out[5]) {
    slot_t *s;
    pthread_mutex_lock(&r->mu);
    s = held(r, k, sid);
    out[0] = s ? s->accepted : 0; out[1] = s ? s->rejected : 0; out[2] = s ? s->superseded : 0;
    out[3] = s ? (uint64_t)s->error : 0; out[4] = s ? (uint64_t)s->proven : 0;
    pthread_mutex_unlock(&r->mu);
}

/* received, accepted, superseded, kernel_dropped, queue_dropped, rate_limited, sources,
 * overflowed, then the rejections per E_* code */
void pf_rx_stats(pf_rx *r, uint64_t out[8 + N_CODES]) {
    int i;
    pthread_mutex_lock(&r->mu);
    out[0] = r->received; out[1] = r->accepted; out[2] = r->superseded;
    out[3] = r->kernel_dropped; out[4] = r->queue_dropped;
    out[5] = r->rate_limited; out[6] = r->sources; out[7] = r->overflowed;
    for (i = 0; i < N_CODES; i++) out[8 + i] = r->counts[i];
    pthread_mutex_unlock(&r->mu);
}

#include "udp_tick.h"   /* the tick's take of a sample and its FEEDBACK (uses pf_rx_sample, pf_rx_feedback) */
