/* pointfence client: UDP session, state out, feedback in (POSIX sockets and clock). */
#ifndef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L
#endif
#include <errno.h>
#include <math.h>
#include <netdb.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <netinet/in.h>
#include <time.h>
#include <unistd.h>
#include <fcntl.h>

#include "pointfence_client.h"

uint64_t pf_now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static int random_bytes(uint8_t *out, size_t n) {
    FILE *f = fopen("/dev/urandom", "rb");
    size_t got;
    if (!f) return PF_E_SYSTEM;
    got = fread(out, 1, n, f);
    fclose(f);
    return got == n ? PF_OK : PF_E_SYSTEM;
}

static int hexval(int ch) {
    if (ch >= '0' && ch <= '9') return ch - '0';
    if (ch >= 'a' && ch <= 'f') return ch - 'a' + 10;
    if (ch >= 'A' && ch <= 'F') return ch - 'A' + 10;
    return -1;
}

int pf_parse_key(const uint8_t *text, size_t n, uint8_t *key, size_t cap, size_t *len) {
    size_t i, k = 0;
    unsigned any = 0;
    if ((!text && n) || !key || !len) return PF_E_ARGUMENT;
    if (n >= 2 && text[n - 2] == '\r' && text[n - 1] == '\n') n -= 2;
    else if (n >= 1 && text[n - 1] == '\n') n -= 1;
    if (n == 0 || n % 2 || n < 32 || n > 2 * PF_KEY_MAX) return PF_E_KEY_FORMAT;
    for (i = 0; i < n; i++)
        if (hexval(text[i]) < 0) return PF_E_KEY_FORMAT;
    if (n / 2 > cap) return PF_E_ARGUMENT;
    for (i = 0; i < n; i += 2) {
        key[k] = (uint8_t)(hexval(text[i]) << 4 | hexval(text[i + 1]));
        any |= key[k++];
    }
    if (!any) { memset(key, 0, k); return PF_E_KEY_ZERO; }
    *len = k;
    return PF_OK;
}

int pf_load_key(const char *path, uint8_t *key, size_t cap, size_t *len) {
    uint8_t text[2 * PF_KEY_MAX + 3];
    struct stat st;
    ssize_t got;
    size_t n = 0;
    int fd, e;
    if (!path || !key || !len) return PF_E_ARGUMENT;
    fd = open(path, O_RDONLY);
    if (fd < 0) return PF_E_SYSTEM;
    if (fstat(fd, &st) != 0) { close(fd); return PF_E_SYSTEM; }
    if (!S_ISREG(st.st_mode)) { close(fd); return PF_E_KEY_FORMAT; }
    if (st.st_mode & 077) { close(fd); return PF_E_KEY_MODE; }
    for (;;) {   /* read up to one byte more than the longest valid file */
        got = read(fd, text + n, sizeof text - n);
        if (got < 0 && errno == EINTR) continue;
        if (got <= 0) break;
        n += (size_t)got;
        if (n == sizeof text) break;
    }
    close(fd);
    if (got < 0) return PF_E_SYSTEM;
    if (n > 2 * PF_KEY_MAX + 2) return PF_E_KEY_FORMAT;
    e = pf_parse_key(text, n, key, cap, len);
    memset(text, 0, sizeof text);
    return e;
}

int pf_client_open(pf_client *c, const char *host, uint16_t port, const uint8_t *psk, size_t psk_len,
                   uint32_t device_id, const pf_hello *caps) {
    struct addrinfo hints, *res = NULL;
    char portstr[8];
    int fd, fl;
    if (!c || !host || !psk || psk_len < 16 || psk_len > PF_KEY_MAX) return PF_E_ARGUMENT;
    memset(c, 0, sizeof *c);
    c->fd = -1;
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_INET;
    hints.ai_socktype = SOCK_DGRAM;
    snprintf(portstr, sizeof portstr, "%u", (unsigned)port);
    if (getaddrinfo(host, portstr, &hints, &res) != 0 || !res) return PF_E_SYSTEM;
    fd = socket(res->ai_family, res->ai_socktype, res->ai_protocol);
    if (fd < 0 || connect(fd, res->ai_addr, res->ai_addrlen) != 0) {
        if (fd >= 0) close(fd);
        freeaddrinfo(res);
        return PF_E_SYSTEM;
    }
    freeaddrinfo(res);
    fl = fcntl(fd, F_GETFL, 0);
    fcntl(fd, F_SETFL, fl | O_NONBLOCK);
    c->fd = fd;
    memcpy(c->psk, psk, psk_len);
    c->psk_len = psk_len;
    c->device_id = device_id;
    c->hello = caps ? *caps : pf_hello_defaults();
    c->timeout_ns = (uint64_t)(c->hello.timeout_ms ? c->hello.timeout_ms : PF_DEFAULT_TIMEOUT_MS) * 1000000u;
    return PF_OK;
}

static void start_session(pf_client *c, uint32_t session, const pf_welcome *w) {
    pf_session_key(c->psk, c->psk_len, c->hello.nonce, w->server_nonce, c->device_id, session, c->key);
    c->session = session;
    c->welcome = *w;
    c->timeout_ns = (uint64_t)w->timeout_ms * 1000000u;
    memset(&c->window, 0, sizeof c->window);
    c->seq = 0;
    c->has_prev = 0;
    c->has_feedback = 0;
    c->have_off = 0;
    c->force[0] = c->force[1] = c->force[2] = 0.0;
    c->last_rx_ns = pf_now_ns();
}

static int send_hello(pf_client *c, uint8_t *buf, size_t cap) {
    size_t len = pf_encode_hello(buf, cap, c->psk, c->psk_len, c->device_id, ++c->hellos, &c->hello);
    if (!len) return PF_E_ARGUMENT;
    (void)send(c->fd, buf, len, 0);
    return PF_OK;
}

/* HELLO (fresh nonce, no cookie) -> COOKIE -> HELLO with the cookie -> WELCOME or REJECT; the
 * handshake restarts with a fresh nonce every 100 ms until timeout_ms. */
int pf_client_connect(pf_client *c, int timeout_ms) {
    uint8_t buf[PF_MAX_DATAGRAM];
    uint64_t end, next = 0;
    if (!c || c->fd < 0) return PF_E_ARGUMENT;
    end = pf_now_ns() + (uint64_t)timeout_ms * 1000000u;
    for (;;) {
        uint64_t now = pf_now_ns();
        struct pollfd pfd;
        ssize_t n;
        pf_header h;
        int wait_ms;
        if (now >= end) return PF_E_TIMEOUT;
        if (now >= next) {   /* (re)start the handshake with a fresh nonce every 100 ms */
            if (random_bytes(c->hello.nonce, PF_NONCE_LEN)) return PF_E_SYSTEM;
            memset(c->hello.cookie, 0, PF_COOKIE_LEN);
            if (send_hello(c, buf, sizeof buf)) return PF_E_ARGUMENT;
            next = now + 100000000u;
        }
        wait_ms = (int)(((next < end ? next : end) - now) / 1000000u) + 1;
        pfd.fd = c->fd; pfd.events = POLLIN; pfd.revents = 0;
        if (poll(&pfd, 1, wait_ms) <= 0) continue;
        n = recv(c->fd, buf, sizeof buf, 0);
        if (n <= 0) continue;
        if (pf_parse_header(buf, (size_t)n, &h) || h.device_id != c->device_id ||
            (h.type != PF_WELCOME && h.type != PF_REJECT && h.type != PF_COOKIE) ||
            pf_verify(buf, (size_t)n, c->psk, c->psk_len)) {
            c->rejected_in++;
            continue;
        }
        if (h.type == PF_COOKIE) {
            pf_cookie k;
            if (pf_decode_cookie(buf, (size_t)n, &k) == PF_OK && !memcmp(k.client_nonce, c->hello.nonce, 16)) {
                memcpy(c->hello.cookie, k.cookie, PF_COOKIE_LEN);
                if (send_hello(c, buf, sizeof buf)) return PF_E_ARGUMENT;
            } else {
                c->rejected_in++;
            }
        } else if (h.type == PF_REJECT) {
            pf_reject r;
            if (pf_decode_reject(buf, (size_t)n, &r) == PF_OK && !memcmp(r.client_nonce, c->hello.nonce, 16))
                return r.error ? r.error : PF_E_MALFORMED;
            c->rejected_in++;
        } else {
            pf_welcome w;
            if (pf_decode_welcome(buf, (size_t)n, &w) == PF_OK && !memcmp(w.client_nonce, c->hello.nonce, 16)) {
                start_session(c, h.session, &w);
                return PF_OK;
            }
            c->rejected_in++;
        }
    }
}

int pf_client_send_state(pf_client *c, pf_state *s) {
    uint8_t buf[PF_STATE_SIZE];
    size_t len;
    int i;
    if (!c || !s) return PF_E_ARGUMENT;
    if (!c->session) return PF_E_NOT_CONNECTED;
    for (i = 0; i < 3; i++) {
        s->increment[i] = c->has_prev ? s->position[i] - c->prev[i] : 0.0;
        c->prev[i] = s->position[i];
    }
    c->has_prev = 1;
    if (!s->t_client_ns) s->t_client_ns = pf_now_ns();
    s->t_echo_ns = c->has_feedback ? c->feedback.t_sent_ns : 0;
    len = pf_encode_state(buf, sizeof buf, c->key, 32, c->device_id, c->session, ++c->seq, s);
    if (!len) return PF_E_ARGUMENT;
    if (send(c->fd, buf, len, 0) < 0 && errno != ECONNREFUSED && errno != EAGAIN) return PF_E_SYSTEM;
    c->sent++;
    return PF_OK;
}

int pf_client_poll(pf_client *c) {
    uint8_t buf[PF_MAX_DATAGRAM];
    int got = 0;
    if (!c) return -PF_E_ARGUMENT;
    if (!c->session) return -PF_E_NOT_CONNECTED;
    for (;;) {
        ssize_t n = recv(c->fd, buf, sizeof buf, 0);
        uint64_t now;
        pf_header h;
        pf_feedback fb;
        if (n < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK) break;
            if (errno == EINTR || errno == ECONNREFUSED) continue;
            return -PF_E_SYSTEM;
        }
        now = pf_now_ns();
        if (pf_parse_header(buf, (size_t)n, &h) || h.session != c->session || h.device_id != c->device_id ||
            pf_verify(buf, (size_t)n, c->key, 32) || pf_window_check(&c->window, h.seq)) {
            c->rejected_in++;
            continue;
        }
        if (h.type == PF_BYE) {          /* the service ended the session */
            pf_window_commit(&c->window, h.seq);
            c->session = 0;
            c->force[0] = c->force[1] = c->force[2] = 0.0;
            return -PF_E_LINK_LOST;
        }
        if (h.type != PF_FEEDBACK || !pf_window_commit(&c->window, h.seq) ||
            pf_decode_feedback(buf, (size_t)n, &fb) != PF_OK) {
            c->rejected_in++;
            continue;
        }
        c->feedback = fb;
        c->has_feedback = 1;
        c->last_rx_ns = now;
        memcpy(c->force, fb.force, sizeof c->force);
        if (!c->have_off || now - fb.t_sent_ns < c->off_ns) { c->off_ns = now - fb.t_sent_ns; c->have_off = 1; }
        c->received++;
        got++;
    }
    if (pf_now_ns() - c->last_rx_ns > c->timeout_ns) c->force[0] = c->force[1] = c->force[2] = 0.0;
    return got;
}

int pf_client_fresh(const pf_client *c) {
    return c && c->session && c->has_feedback && pf_now_ns() - c->last_rx_ns <= c->timeout_ns;
}

int pf_client_force(const pf_client *c, double f[3]) {
    if (!f) return 0;
    if (pf_client_fresh(c)) {
        f[0] = c->force[0]; f[1] = c->force[1]; f[2] = c->force[2];
        return 1;
    }
    f[0] = f[1] = f[2] = 0.0;
    return 0;
}

uint64_t pf_client_next_tick_ns(const pf_client *c, uint64_t after_ns) {
    double period, g0, k;
    if (!c || !c->has_feedback || !c->have_off || c->welcome.rate_hz <= 0) return 0;
    period = 1e9 / c->welcome.rate_hz;
    g0 = (double)(c->feedback.t_tick_ns + c->off_ns);
    k = ceil(((double)after_ns - g0) / period);
    return (uint64_t)(g0 + k * period);
}

void pf_client_close(pf_client *c) {
    if (!c) return;
    if (c->session && c->fd >= 0) {
        uint8_t buf[PF_BYE_SIZE];
        pf_bye b;
        b.reason = PF_OK;
        if (pf_encode_bye(buf, sizeof buf, c->key, 32, c->device_id, c->session, ++c->seq, &b))
            (void)send(c->fd, buf, sizeof buf, 0);
    }
    c->session = 0;
    c->force[0] = c->force[1] = c->force[2] = 0.0;
    if (c->fd >= 0) close(c->fd);
    c->fd = -1;
    memset(c->psk, 0, sizeof c->psk);
    memset(c->key, 0, sizeof c->key);
}
