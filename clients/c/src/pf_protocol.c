/* pointfence wire protocol v2: encoding, checks and decoding (see clients/PROTOCOL.md). */
#include <math.h>
#include <string.h>

#include "pointfence_client.h"

#define MAX_FORCE_N 1000.0
#define MAX_EXTENT_M 10.0
#define MAX_RATE_HZ 10000.0
#define MAX_TIMEOUT_MS 1000
#define WORKSPACE_MARGIN_M 0.001
#define QUAT_TOL 1e-3

/* ---- little-endian primitives (byte by byte: correct on any host) ---- */
static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { int i; for (i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i)); }
static void put64(uint8_t *p, uint64_t v) { int i; for (i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i)); }
static void putd(uint8_t *p, double d) { uint64_t v; memcpy(&v, &d, 8); put64(p, v); }
static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | p[1] << 8); }
static uint32_t get32(const uint8_t *p) { return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24; }
static uint64_t get64(const uint8_t *p) { return (uint64_t)get32(p) | (uint64_t)get32(p + 4) << 32; }
static double getd(const uint8_t *p) { uint64_t v = get64(p); double d; memcpy(&d, &v, 8); return d; }

static size_t type_size(int t) {
    switch (t) {
    case PF_HELLO: return PF_HELLO_SIZE;
    case PF_WELCOME: return PF_WELCOME_SIZE;
    case PF_REJECT: return PF_REJECT_SIZE;
    case PF_STATE: return PF_STATE_SIZE;
    case PF_FEEDBACK: return PF_FEEDBACK_SIZE;
    case PF_BYE: return PF_BYE_SIZE;
    case PF_COOKIE: return PF_COOKIE_SIZE;
    default: return 0;
    }
}

const char *pf_error_name(int code) {
    static const char *names[] = {"ok", "malformed", "version", "truncated", "oversized", "auth", "replay",
                                  "stale", "no_session", "non_finite", "workspace", "full", "busy", "timeout",
                                  "capability", "direction", "cookie"};
    if (code >= 0 && code <= PF_E_COOKIE) return names[code];
    switch (code) {
    case PF_E_ARGUMENT: return "argument";
    case PF_E_SYSTEM: return "system";
    case PF_E_NOT_CONNECTED: return "not_connected";
    case PF_E_LINK_LOST: return "link_lost";
    case PF_E_KEY_MODE: return "key_mode";
    case PF_E_KEY_FORMAT: return "key_format";
    case PF_E_KEY_ZERO: return "key_zero";
    default: return "unknown";
    }
}

pf_hello pf_hello_defaults(void) {
    pf_hello h;
    int i;
    memset(&h, 0, sizeof h);
    h.max_force = 3.3;
    for (i = 0; i < 3; i++) { h.workspace_min[i] = -0.1; h.workspace_max[i] = 0.1; }
    h.rate_hz = 1000.0;
    h.timeout_ms = PF_DEFAULT_TIMEOUT_MS;
    h.caps = PF_CAP_FORCE | PF_CAP_CLUTCH;
    strcpy(h.model, "c-sdk");
    return h;
}

pf_state pf_state_defaults(void) {
    pf_state s;
    memset(&s, 0, sizeof s);
    s.orientation[0] = 1.0;
    s.flags = PF_F_CLUTCH;
    return s;
}

/* ---- encoding ---- */
static uint8_t *head(uint8_t *out, int type, uint32_t dev, uint32_t session, uint64_t seq) {
    out[0] = 'P'; out[1] = 'F'; out[2] = PF_PROTOCOL_VERSION; out[3] = (uint8_t)type;
    put32(out + 4, dev); put32(out + 8, session); put64(out + 12, seq); put32(out + 20, 0);
    return out + PF_HEADER_LEN;
}

static size_t seal(uint8_t *out, size_t size, const uint8_t *key, size_t key_len) {
    uint8_t mac[32];
    pf_hmac_sha256(key, key_len, out, size - PF_TAG_LEN, mac);
    memcpy(out + size - PF_TAG_LEN, mac, PF_TAG_LEN);
    return size;
}

#define CHECK_OUT(sz) do { if (!out || cap < (sz) || !key || !key_len || !m) return 0; } while (0)

size_t pf_encode_hello(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint64_t seq,
                       const pf_hello *m) {
    uint8_t *p;
    size_t n;
    int i;
    CHECK_OUT(PF_HELLO_SIZE);
    p = head(out, PF_HELLO, dev, 0, seq);
    memcpy(p, m->nonce, 16);
    putd(p + 16, m->max_force);
    for (i = 0; i < 3; i++) { putd(p + 24 + 8 * i, m->workspace_min[i]); putd(p + 48 + 8 * i, m->workspace_max[i]); }
    putd(p + 72, m->rate_hz);
    put16(p + 80, m->timeout_ms);
    put16(p + 82, m->caps);
    put32(p + 84, 0);
    memset(p + 88, 0, 16);
    n = strlen(m->model);
    memcpy(p + 88, m->model, n > 16 ? 16 : n);
    memcpy(p + 104, m->cookie, PF_COOKIE_LEN);
    return seal(out, PF_HELLO_SIZE, key, key_len);
}

size_t pf_encode_welcome(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint32_t session,
                         uint64_t seq, const pf_welcome *m) {
    uint8_t *p;
    CHECK_OUT(PF_WELCOME_SIZE);
    p = head(out, PF_WELCOME, dev, session, seq);
    memcpy(p, m->client_nonce, 16);
    memcpy(p + 16, m->server_nonce, 16);
    put16(p + 32, m->slot); put16(p + 34, m->timeout_ms); put32(p + 36, 0);
    putd(p + 40, m->rate_hz); putd(p + 48, m->max_force); put64(p + 56, m->t_service_ns);
    return seal(out, PF_WELCOME_SIZE, key, key_len);
}

size_t pf_encode_reject(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint64_t seq,
                        const pf_reject *m) {
    uint8_t *p;
    CHECK_OUT(PF_REJECT_SIZE);
    p = head(out, PF_REJECT, dev, 0, seq);
    memcpy(p, m->client_nonce, 16);
    put16(p + 16, m->error); put16(p + 18, 0); put32(p + 20, 0);
    return seal(out, PF_REJECT_SIZE, key, key_len);
}

size_t pf_encode_state(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint32_t session,
                       uint64_t seq, const pf_state *m) {
    uint8_t *p;
    int i;
    CHECK_OUT(PF_STATE_SIZE);
    p = head(out, PF_STATE, dev, session, seq);
    put64(p, m->t_client_ns); put64(p + 8, m->t_echo_ns);
    for (i = 0; i < 3; i++) { putd(p + 16 + 8 * i, m->position[i]); putd(p + 40 + 8 * i, m->increment[i]); }
    for (i = 0; i < 4; i++) putd(p + 64 + 8 * i, m->orientation[i]);
    putd(p + 96, m->grasp);
    put32(p + 104, m->buttons); put16(p + 108, m->flags); put16(p + 110, 0);
    return seal(out, PF_STATE_SIZE, key, key_len);
}

size_t pf_encode_feedback(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev,
                          uint32_t session, uint64_t seq, const pf_feedback *m) {
    uint8_t *p;
    int i;
    CHECK_OUT(PF_FEEDBACK_SIZE);
    p = head(out, PF_FEEDBACK, dev, session, seq);
    put64(p, m->tick); put64(p + 8, m->t_tick_ns); put64(p + 16, m->t_sent_ns); put64(p + 24, m->echo_seq);
    put64(p + 32, m->echo_t_client_ns);
    for (i = 0; i < 3; i++) {
        putd(p + 40 + 8 * i, m->force[i]); putd(p + 64 + 8 * i, m->proxy[i]); putd(p + 88 + 8 * i, m->robot[i]);
    }
    p[112] = m->contact; p[113] = m->fixture; p[114] = m->robot_mode; p[115] = m->link;
    put32(p + 116, m->hold); put16(p + 120, m->error); put16(p + 122, m->slot); put32(p + 124, m->rejected);
    put32(p + 128, 0);
    return seal(out, PF_FEEDBACK_SIZE, key, key_len);
}

size_t pf_encode_bye(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint32_t session,
                     uint64_t seq, const pf_bye *m) {
    uint8_t *p;
    CHECK_OUT(PF_BYE_SIZE);
    p = head(out, PF_BYE, dev, session, seq);
    put16(p, m->reason); put16(p + 2, 0); put32(p + 4, 0);
    return seal(out, PF_BYE_SIZE, key, key_len);
}

size_t pf_encode_cookie(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t dev, uint64_t seq,
                        const pf_cookie *m) {
    uint8_t *p;
    CHECK_OUT(PF_COOKIE_SIZE);
    p = head(out, PF_COOKIE, dev, 0, seq);
    memcpy(p, m->client_nonce, 16);
    memcpy(p + 16, m->cookie, PF_COOKIE_LEN);
    return seal(out, PF_COOKIE_SIZE, key, key_len);
}

/* ---- checks ---- */
int pf_parse_header(const uint8_t *buf, size_t len, pf_header *h) {
    size_t size;
    if (!buf && len) return PF_E_ARGUMENT;
    if (len < PF_HEADER_LEN + PF_TAG_LEN) return PF_E_TRUNCATED;
    if (buf[0] != 'P' || buf[1] != 'F') return PF_E_MALFORMED;
    if (buf[2] != PF_PROTOCOL_VERSION) return PF_E_VERSION;
    size = type_size(buf[3]);
    if (!size) return PF_E_MALFORMED;
    if (len < size) return PF_E_TRUNCATED;
    if (len > size) return PF_E_OVERSIZED;
    if (get32(buf + 20)) return PF_E_MALFORMED;
    if (h) {
        h->type = buf[3]; h->device_id = get32(buf + 4); h->session = get32(buf + 8); h->seq = get64(buf + 12);
    }
    return PF_OK;
}

int pf_verify(const uint8_t *buf, size_t len, const uint8_t *key, size_t key_len) {
    uint8_t mac[32];
    unsigned diff = 0;
    int i;
    if (!buf || len < PF_HEADER_LEN + PF_TAG_LEN || !key) return PF_E_ARGUMENT;
    pf_hmac_sha256(key, key_len, buf, len - PF_TAG_LEN, mac);
    for (i = 0; i < PF_TAG_LEN; i++) diff |= (unsigned)(mac[i] ^ buf[len - PF_TAG_LEN + i]);
    return diff ? PF_E_AUTH : PF_OK;
}

static int all_finite(const double *v, int n) {
    int i;
    for (i = 0; i < n; i++)
        if (!isfinite(v[i])) return 0;
    return 1;
}

int pf_decode_hello(const uint8_t *buf, size_t len, pf_hello *m) {
    const uint8_t *p;
    double v[8];
    uint32_t rsv;
    int i, last;
    if (!buf || !m || len != PF_HELLO_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    memcpy(m->nonce, p, 16);
    m->max_force = getd(p + 16);
    for (i = 0; i < 3; i++) { m->workspace_min[i] = getd(p + 24 + 8 * i); m->workspace_max[i] = getd(p + 48 + 8 * i); }
    m->rate_hz = getd(p + 72);
    m->timeout_ms = get16(p + 80);
    m->caps = get16(p + 82);
    rsv = get32(p + 84);
    v[0] = m->max_force;
    for (i = 0; i < 3; i++) { v[1 + i] = m->workspace_min[i]; v[4 + i] = m->workspace_max[i]; }
    v[7] = m->rate_hz;
    if (!all_finite(v, 8)) return PF_E_NON_FINITE;
    if (rsv || (m->caps & ~0xFu)) return PF_E_MALFORMED;
    last = -1;
    for (i = 0; i < 16; i++)
        if (p[88 + i]) last = i;
    for (i = 0; i <= last; i++)
        if (p[88 + i] < 0x20 || p[88 + i] > 0x7E) return PF_E_MALFORMED;
    memset(m->model, 0, sizeof m->model);
    memcpy(m->model, p + 88, (size_t)(last + 1));
    memcpy(m->cookie, p + 104, PF_COOKIE_LEN);
    if (!(m->max_force > 0 && m->max_force <= MAX_FORCE_N)) return PF_E_CAPABILITY;
    for (i = 0; i < 3; i++)
        if (!(-MAX_EXTENT_M <= m->workspace_min[i] && m->workspace_min[i] < m->workspace_max[i] &&
              m->workspace_max[i] <= MAX_EXTENT_M)) return PF_E_CAPABILITY;
    if (!(m->rate_hz >= 1.0 && m->rate_hz <= MAX_RATE_HZ)) return PF_E_CAPABILITY;
    if (m->timeout_ms > MAX_TIMEOUT_MS) return PF_E_CAPABILITY;
    return PF_OK;
}

int pf_decode_welcome(const uint8_t *buf, size_t len, pf_welcome *m) {
    const uint8_t *p;
    double v[2];
    if (!buf || !m || len != PF_WELCOME_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    memcpy(m->client_nonce, p, 16); memcpy(m->server_nonce, p + 16, 16);
    m->slot = get16(p + 32); m->timeout_ms = get16(p + 34);
    m->rate_hz = getd(p + 40); m->max_force = getd(p + 48); m->t_service_ns = get64(p + 56);
    v[0] = m->rate_hz; v[1] = m->max_force;
    if (!all_finite(v, 2)) return PF_E_NON_FINITE;
    if (get32(p + 36)) return PF_E_MALFORMED;
    if (!(m->timeout_ms >= 1 && m->timeout_ms <= MAX_TIMEOUT_MS && m->rate_hz >= 1.0 && m->rate_hz <= MAX_RATE_HZ &&
          m->max_force >= 0 && m->max_force <= MAX_FORCE_N)) return PF_E_CAPABILITY;
    return PF_OK;
}

int pf_decode_reject(const uint8_t *buf, size_t len, pf_reject *m) {
    const uint8_t *p;
    if (!buf || !m || len != PF_REJECT_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    memcpy(m->client_nonce, p, 16);
    m->error = get16(p + 16);
    if (get16(p + 18) || get32(p + 20)) return PF_E_MALFORMED;
    return PF_OK;
}

int pf_decode_state(const uint8_t *buf, size_t len, const double *lo, const double *hi, pf_state *m) {
    const uint8_t *p;
    double v[11];
    int i;
    if (!buf || !m || len != PF_STATE_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    m->t_client_ns = get64(p); m->t_echo_ns = get64(p + 8);
    for (i = 0; i < 3; i++) { m->position[i] = getd(p + 16 + 8 * i); m->increment[i] = getd(p + 40 + 8 * i); }
    for (i = 0; i < 4; i++) m->orientation[i] = getd(p + 64 + 8 * i);
    m->grasp = getd(p + 96);
    m->buttons = get32(p + 104); m->flags = get16(p + 108);
    if (get16(p + 110) || (m->flags & ~0x7u)) return PF_E_MALFORMED;
    for (i = 0; i < 3; i++) { v[i] = m->position[i]; v[3 + i] = m->increment[i]; }
    for (i = 0; i < 4; i++) v[6 + i] = m->orientation[i];
    v[10] = m->grasp;
    if (!all_finite(v, 11)) return PF_E_NON_FINITE;
    if (lo && hi) {
        for (i = 0; i < 3; i++) {
            if (!(lo[i] - WORKSPACE_MARGIN_M <= m->position[i] && m->position[i] <= hi[i] + WORKSPACE_MARGIN_M))
                return PF_E_WORKSPACE;
            if (fabs(m->increment[i]) > hi[i] - lo[i] + 2 * WORKSPACE_MARGIN_M) return PF_E_WORKSPACE;
        }
    } else {
        for (i = 0; i < 3; i++)
            if (fabs(m->position[i]) > MAX_EXTENT_M || fabs(m->increment[i]) > 2 * MAX_EXTENT_M) return PF_E_WORKSPACE;
    }
    if (m->flags & PF_F_ORIENTATION) {
        const double *q = m->orientation;
        double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (fabs(n - 1.0) > QUAT_TOL) return PF_E_WORKSPACE;
    }
    return PF_OK;
}

int pf_decode_feedback(const uint8_t *buf, size_t len, pf_feedback *m) {
    const uint8_t *p;
    double v[9];
    int i;
    if (!buf || !m || len != PF_FEEDBACK_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    m->tick = get64(p); m->t_tick_ns = get64(p + 8); m->t_sent_ns = get64(p + 16); m->echo_seq = get64(p + 24);
    m->echo_t_client_ns = get64(p + 32);
    for (i = 0; i < 3; i++) {
        m->force[i] = getd(p + 40 + 8 * i); m->proxy[i] = getd(p + 64 + 8 * i); m->robot[i] = getd(p + 88 + 8 * i);
        v[i] = m->force[i]; v[3 + i] = m->proxy[i]; v[6 + i] = m->robot[i];
    }
    m->contact = p[112]; m->fixture = p[113]; m->robot_mode = p[114]; m->link = p[115];
    m->hold = get32(p + 116); m->error = get16(p + 120); m->slot = get16(p + 122); m->rejected = get32(p + 124);
    if (get32(p + 128)) return PF_E_MALFORMED;
    if (!all_finite(v, 9)) return PF_E_NON_FINITE;
    return PF_OK;
}

int pf_decode_bye(const uint8_t *buf, size_t len, pf_bye *m) {
    const uint8_t *p;
    if (!buf || !m || len != PF_BYE_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    m->reason = get16(p);
    if (get16(p + 2) || get32(p + 4)) return PF_E_MALFORMED;
    return PF_OK;
}

int pf_decode_cookie(const uint8_t *buf, size_t len, pf_cookie *m) {
    const uint8_t *p;
    int i, any = 0;
    if (!buf || !m || len != PF_COOKIE_SIZE) return PF_E_ARGUMENT;
    p = buf + PF_HEADER_LEN;
    memcpy(m->client_nonce, p, 16);
    memcpy(m->cookie, p + 16, PF_COOKIE_LEN);
    for (i = 0; i < PF_COOKIE_LEN; i++) any |= m->cookie[i];
    return any ? PF_OK : PF_E_MALFORMED;
}

int pf_decode(const uint8_t *buf, size_t len, const uint8_t *key, size_t key_len, const double *ws_min,
              const double *ws_max, pf_header *h, pf_message *m) {
    pf_header hh;
    int e = pf_parse_header(buf, len, &hh);
    if (e) return e;
    if (h) *h = hh;
    e = pf_verify(buf, len, key, key_len);
    if (e) return e;
    if (!m) return PF_E_ARGUMENT;
    switch (hh.type) {
    case PF_HELLO: return pf_decode_hello(buf, len, &m->hello);
    case PF_WELCOME: return pf_decode_welcome(buf, len, &m->welcome);
    case PF_REJECT: return pf_decode_reject(buf, len, &m->reject);
    case PF_STATE: return pf_decode_state(buf, len, ws_min, ws_max, &m->state);
    case PF_FEEDBACK: return pf_decode_feedback(buf, len, &m->feedback);
    case PF_COOKIE: return pf_decode_cookie(buf, len, &m->cookie);
    default: return pf_decode_bye(buf, len, &m->bye);
    }
}

/* ---- replay window ---- */
int pf_window_check(const pf_window *w, uint64_t seq) {
    uint64_t d;
    if (seq == 0) return PF_E_STALE;
    if (seq > w->top) return PF_OK;
    d = w->top - seq;
    if (d >= PF_WINDOW) return PF_E_STALE;
    if ((w->bits >> d) & 1u) return PF_E_REPLAY;
    return PF_OK;
}

int pf_window_commit(pf_window *w, uint64_t seq) {
    if (seq > w->top) {
        uint64_t shift = seq - w->top;
        w->bits = shift < 64 ? (w->bits << shift) | 1u : 1u;
        w->top = seq;
        return 1;
    }
    w->bits |= (uint64_t)1 << (w->top - seq);
    return 0;
}
