/* One session of the UDP receiver (native/udp_rx.c, which includes this file): its slot, and the
 * checks of a STATE that names it (anti-replay window, tag, values) and the publishing of its
 * sample. Static functions on one slot_t; the caller holds the receiver's mutex.
 *
 * A STATE (clients/PROTOCOL.md; little-endian): header magic "PF" @0, version u8 @2, type u8
 * @3, device u32 @4, session u32 @8, seq u64 @12, reserved u32 @20; payload t_client u64 @24,
 * t_echo u64 @32, position 3 f64 @40 (m), increment 3 f64 @64 (m), quaternion w x y z 4 f64
 * @88, grasp f64 @120, buttons u32 @128, flags u16 @132, reserved u16 @134; tag @136..152.
 */
#ifndef PF_UDP_RX_SESSION_H
#define PF_UDP_RX_SESSION_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#include "pointfence_client.h"

/* protocol constants beyond the C client's header (clients/protocol.py) */
#define PF_BODY (PF_STATE_SIZE - PF_TAG_LEN)   /* bytes under the tag */
#define PF_FLAG_MASK 0x7u
#define PF_WS_MARGIN 0.001          /* WORKSPACE_MARGIN_M */
#define PF_QUAT_TOL 1e-3
#define N_CODES (PF_E_COOKIE + 1)

typedef struct {
    /* the session (set by pf_rx_open under the mutex) */
    uint32_t live, sid, dev, ip, port;
    uint8_t key[PF_KEY_MAX];        /* the session key (FEEDBACK is tagged with it) */
    int32_t keylen;
    double max_force;               /* N: FEEDBACK's force is saturated to it */
    uint64_t tx;                    /* the service's last sequence number in this session */
    pf_sha256_ctx ictx, octx;       /* HMAC key pads, hashed once per session */
    double ws_lo[3], ws_hi[3];
    pf_window win;                  /* anti-replay window (the C client's), under the mutex */
    uint64_t accepted, rejected, superseded;
    int32_t error, proven;
    /* the latest sample: seqlock (odd while written) */
    uint64_t sl;
    uint64_t n, seq, t_client;
    int64_t rx_ns;
    double pos[3], quat[4], grasp;
    uint32_t flags, buttons;
} slot_t;

static uint64_t rd64(const uint8_t *p) { uint64_t v; memcpy(&v, p, 8); return v; }
static uint32_t rd32(const uint8_t *p) { uint32_t v; memcpy(&v, p, 4); return v; }
static uint16_t rd16(const uint8_t *p) { uint16_t v; memcpy(&v, p, 2); return v; }
static double rdf(const uint8_t *p) { double v; memcpy(&v, p, 8); return v; }

static int tag_ok(const slot_t *s, const uint8_t *d) {
    pf_sha256_ctx c;
    uint8_t inner[32], mac[32];
    unsigned diff = 0;
    int i;
    c = s->ictx; pf_sha256_update(&c, d, PF_BODY); pf_sha256_final(&c, inner);
    c = s->octx; pf_sha256_update(&c, inner, 32); pf_sha256_final(&c, mac);
    for (i = 0; i < PF_TAG_LEN; i++) diff |= (unsigned)(mac[i] ^ d[PF_BODY + i]);
    return diff == 0;
}

/* the value checks of protocol.State.decode and check_state_values */
static int values_ok(const slot_t *s, const uint8_t *d) {
    double v[11], nq;
    uint32_t flags = rd16(d + 132);
    int i;
    if (rd16(d + 134) != 0 || (flags & ~PF_FLAG_MASK)) return PF_E_MALFORMED;
    for (i = 0; i < 11; i++) {
        v[i] = rdf(d + 40 + 8 * i);
        if (!isfinite(v[i])) return PF_E_NON_FINITE;
    }
    for (i = 0; i < 3; i++) {
        if (!(s->ws_lo[i] - PF_WS_MARGIN <= v[i] && v[i] <= s->ws_hi[i] + PF_WS_MARGIN)) return PF_E_WORKSPACE;
        if (fabs(v[3 + i]) > s->ws_hi[i] - s->ws_lo[i] + 2 * PF_WS_MARGIN) return PF_E_WORKSPACE;
    }
    if (flags & PF_F_ORIENTATION) {
        nq = sqrt(v[6] * v[6] + v[7] * v[7] + v[8] * v[8] + v[9] * v[9]);
        if (fabs(nq - 1.0) > PF_QUAT_TOL) return PF_E_WORKSPACE;
    }
    return PF_OK;
}

static void publish(slot_t *s, const uint8_t *d, int64_t rx_ns) {
    uint32_t flags = rd16(d + 132);
    int i;
    __atomic_store_n(&s->sl, s->sl + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
    s->seq = rd64(d + 12);
    for (i = 0; i < 3; i++) s->pos[i] = rdf(d + 40 + 8 * i);
    if (flags & PF_F_ORIENTATION) for (i = 0; i < 4; i++) s->quat[i] = rdf(d + 88 + 8 * i);
    if (flags & PF_F_GRASP) s->grasp = rdf(d + 120);
    s->flags = flags;
    s->buttons = rd32(d + 128);
    s->t_client = rd64(d + 24);
    s->rx_ns = rx_ns;
    s->n += 1;
    __atomic_thread_fence(__ATOMIC_RELEASE);
    __atomic_store_n(&s->sl, s->sl + 1, __ATOMIC_RELEASE);
}

#endif
