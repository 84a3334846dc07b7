/* The client against a minimal service written with the same codec (a forked process on
 * loopback): handshake (HELLO, COOKIE, HELLO with the cookie, WELCOME), states out, feedback in, stale-link force zeroing, spoofed feedback
 * rejected, BYE. */
#ifndef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L
#endif
#include <arpa/inet.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include "pointfence_client.h"

static const uint8_t PSK[32] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16,
                                17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32};
static int failures;
#define EXPECT(c, msg) do { if (!(c)) { failures++; fprintf(stderr, "FAIL: %s\n", msg); } } while (0)

/* the mini service: one session; answers each STATE with a FEEDBACK whose force is -100 x position;
 * after a STATE with buttons == 99 it goes silent; after a BYE it exits */
static void serve(int fd) {
    uint8_t buf[PF_MAX_DATAGRAM], out[PF_MAX_DATAGRAM], skey[32];
    struct sockaddr_in peer; socklen_t pl;
    uint32_t session = 0x5E55; uint64_t tx = 0; int silent = 0;
    pf_window win; memset(&win, 0, sizeof win);
    for (;;) {
        pf_header h; pf_message m; ssize_t n;
        pl = sizeof peer;
        n = recvfrom(fd, buf, sizeof buf, 0, (struct sockaddr *)&peer, &pl);
        if (n <= 0 || pf_parse_header(buf, (size_t)n, &h)) continue;
        if (h.type == PF_HELLO) {
            pf_welcome w; pf_cookie ck; size_t len; int i;
            if (pf_decode(buf, (size_t)n, PSK, 32, NULL, NULL, &h, &m)) continue;
            /* the challenge: a cookie derived from the nonce; only a HELLO repeating it opens the session */
            memcpy(ck.client_nonce, m.hello.nonce, 16);
            for (i = 0; i < PF_COOKIE_LEN; i++) ck.cookie[i] = (uint8_t)(m.hello.nonce[i % 16] ^ 0xC5 ^ i);
            if (memcmp(m.hello.cookie, ck.cookie, PF_COOKIE_LEN)) {
                len = pf_encode_cookie(out, sizeof out, PSK, 32, h.device_id, 0, &ck);
                sendto(fd, out, len, 0, (struct sockaddr *)&peer, pl);
                continue;
            }
            memcpy(w.client_nonce, m.hello.nonce, 16);
            memset(w.server_nonce, 0xAB, 16);
            w.slot = 0; w.timeout_ms = 50; w.rate_hz = 1000; w.max_force = 3; w.t_service_ns = 0;
            pf_session_key(PSK, 32, m.hello.nonce, w.server_nonce, h.device_id, session, skey);
            len = pf_encode_welcome(out, sizeof out, PSK, 32, h.device_id, session, 0, &w);
            sendto(fd, out, len, 0, (struct sockaddr *)&peer, pl);
        } else if (h.type == PF_STATE || h.type == PF_BYE) {
            pf_feedback fb; size_t len; int i;
            if (h.session != session || pf_decode(buf, (size_t)n, skey, 32, NULL, NULL, &h, &m)) continue;
            if (pf_window_check(&win, h.seq)) continue;
            pf_window_commit(&win, h.seq);
            if (h.type == PF_BYE) _exit(0);
            if (m.state.buttons == 99) silent = 1;
            if (silent) continue;
            memset(&fb, 0, sizeof fb);
            for (i = 0; i < 3; i++) fb.force[i] = -100.0 * m.state.position[i];
            fb.echo_seq = h.seq; fb.t_sent_ns = pf_now_ns(); fb.t_tick_ns = fb.t_sent_ns;
            len = pf_encode_feedback(out, sizeof out, skey, 32, h.device_id, session, ++tx, &fb);
            sendto(fd, out, len, 0, (struct sockaddr *)&peer, pl);
            /* a spoofed feedback (wrong key) right after: the client must drop it */
            memset(fb.force, 0, sizeof fb.force); fb.force[0] = 99.0;
            len = pf_encode_feedback(out, sizeof out, PSK, 32, h.device_id, session, ++tx, &fb);
            sendto(fd, out, len, 0, (struct sockaddr *)&peer, pl);
        }
    }
}

static void sleep_ms(int ms) { struct timespec ts; ts.tv_sec = ms / 1000; ts.tv_nsec = (long)(ms % 1000) * 1000000L; nanosleep(&ts, NULL); }

int main(void) {
    struct sockaddr_in a; socklen_t al = sizeof a;
    int fd = socket(AF_INET, SOCK_DGRAM, 0), i, status;
    pid_t pid;
    pf_client c; pf_hello caps = pf_hello_defaults(); pf_state s;
    double f[3];
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET; a.sin_addr.s_addr = htonl(INADDR_LOOPBACK); a.sin_port = 0;
    if (fd < 0 || bind(fd, (struct sockaddr *)&a, sizeof a) || getsockname(fd, (struct sockaddr *)&a, &al)) return 2;
    pid = fork();
    if (pid == 0) { serve(fd); _exit(0); }
    close(fd);
    EXPECT(pf_client_open(&c, "127.0.0.1", ntohs(a.sin_port), PSK, 32, 42, &caps) == PF_OK, "open");
    EXPECT(pf_client_send_state(&c, &s) == PF_E_NOT_CONNECTED, "send before connect refused");
    EXPECT(pf_client_connect(&c, 3000) == PF_OK, "connect");
    EXPECT(c.session == 0x5E55, "session id from WELCOME");
    for (i = 0; i < 20; i++) {
        s = pf_state_defaults();
        s.position[0] = 0.001 * i; s.position[2] = -0.01;
        EXPECT(pf_client_send_state(&c, &s) == PF_OK, "send");
        sleep_ms(2);
        pf_client_poll(&c);
    }
    EXPECT(pf_client_force(&c, f) == 1, "fresh feedback");
    EXPECT(f[0] == -100.0 * (0.001 * 19) && f[2] > 0.999999 && f[2] < 1.000001, "force of the newest sample (spoofed feedback ignored)");
    EXPECT(c.rejected_in >= 19, "spoofed feedback counted as rejected");
    EXPECT(c.feedback.echo_seq == 20, "echo of the last sequence");
    s = pf_state_defaults(); s.buttons = 99;         /* the service goes silent */
    pf_client_send_state(&c, &s);
    sleep_ms(80);
    pf_client_poll(&c);
    EXPECT(pf_client_force(&c, f) == 0 && f[0] == 0.0 && f[1] == 0.0 && f[2] == 0.0, "stale link: zero force");
    pf_client_close(&c);
    for (i = 0; i < 200 && waitpid(pid, &status, WNOHANG) == 0; i++) sleep_ms(10);
    if (i == 200) { kill(pid, SIGKILL); waitpid(pid, &status, 0); EXPECT(0, "service got the BYE"); }
    printf("loopback: %d failures\n", failures);
    return failures ? 1 : 0;
}
