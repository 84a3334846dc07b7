/* The protocol test vectors (clients/vectors, *.json), byte for byte, through the C SDK. */
#ifndef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L
#endif
#include <math.h>
#include <sys/stat.h>
#include <unistd.h>
#include "minijson.h"
#include "pointfence_client.h"

static int failures, checks;
#define EXPECT(cond, ...) do { checks++; if (!(cond)) { failures++; fprintf(stderr, "FAIL: " __VA_ARGS__); fputc('\n', stderr); } } while (0)

static char dir[1024];
static const char *path(const char *name) { static char p[1200]; snprintf(p, sizeof p, "%s/%s", dir, name); return p; }

static void hexstr(const uint8_t *b, size_t n, char *out) { size_t i; for (i = 0; i < n; i++) sprintf(out + 2 * i, "%02x", b[i]); out[2 * n] = 0; }

static void test_sha256(void) {
    int root = j_load(path("sha256.json")), cases = j_get(root, "cases"), i;
    static uint8_t msg[4096];
    for (i = 0; i < j_count(cases); i++) {
        int c = j_at(cases, i);
        uint8_t d[32], want[32];
        size_t n = j_hex(j_get(c, "message_hex"), msg, sizeof msg);
        pf_sha256(msg, n, d);
        j_hex(j_get(c, "digest_hex"), want, 32);
        EXPECT(!memcmp(d, want, 32), "sha256 case %d", i);
        { /* byte-at-a-time updates give the same digest */
            pf_sha256_ctx ctx; size_t k; uint8_t d2[32];
            pf_sha256_init(&ctx);
            for (k = 0; k < n; k++) pf_sha256_update(&ctx, msg + k, 1);
            pf_sha256_final(&ctx, d2);
            EXPECT(!memcmp(d2, want, 32), "sha256 incremental case %d", i);
        }
    }
}

static void test_hmac(void) {
    int root = j_load(path("hmac_sha256.json")), cases = j_get(root, "cases"), i;
    for (i = 0; i < j_count(cases); i++) {
        int c = j_at(cases, i);
        uint8_t key[256], data[512], mac[32], want[32];
        size_t kn = j_hex(j_get(c, "key_hex"), key, sizeof key), dn = j_hex(j_get(c, "data_hex"), data, sizeof data);
        pf_hmac_sha256(key, kn, data, dn, mac);
        j_hex(j_get(c, "mac_hex"), want, 32);
        EXPECT(!memcmp(mac, want, 32), "hmac case %d", i);
    }
}

static void test_session_keys(void) {
    int root = j_load(path("session_keys.json")), cases = j_get(root, "cases"), i;
    for (i = 0; i < j_count(cases); i++) {
        int c = j_at(cases, i);
        uint8_t psk[64], cn[16], sn[16], k[32], want[32];
        size_t pn = j_hex(j_get(c, "psk_hex"), psk, sizeof psk);
        j_hex(j_get(c, "client_nonce_hex"), cn, 16);
        j_hex(j_get(c, "server_nonce_hex"), sn, 16);
        pf_session_key(psk, pn, cn, sn, (uint32_t)j_u64(j_get(c, "device_id")), (uint32_t)j_u64(j_get(c, "session")), k);
        j_hex(j_get(c, "session_key_hex"), want, 32);
        EXPECT(!memcmp(k, want, 32), "session key case %d", i);
    }
}

static void vec3(int f, const char *key, double *out, int n) { int i; for (i = 0; i < n; i++) out[i] = j_numat(f, key, i); }

static void test_messages(void) {
    int root = j_load(path("messages.json")), vs = j_get(root, "vectors"), i;
    for (i = 0; i < j_count(vs); i++) {
        int v = j_at(vs, i), f = j_get(v, "fields");
        char type[16], name[64], got_hex[1024], want_hex[1024];
        uint8_t key[64], out[PF_MAX_DATAGRAM], want[PF_MAX_DATAGRAM];
        size_t kn = j_hex(j_get(v, "key_hex"), key, sizeof key), n = 0, wn;
        uint32_t dev = (uint32_t)j_u64(j_get(v, "device_id")), sess = (uint32_t)j_u64(j_get(v, "session"));
        uint64_t seq = j_u64(j_get(v, "seq"));
        pf_header h; pf_message m; int e;
        j_str(j_get(v, "type"), type, sizeof type);
        j_str(j_get(v, "name"), name, sizeof name);
        wn = j_hex(j_get(v, "bytes_hex"), want, sizeof want);
        if (!strcmp(type, "HELLO")) {
            pf_hello x; memset(&x, 0, sizeof x);
            j_hex(j_get(f, "nonce_hex"), x.nonce, 16);
            x.max_force = j_num(j_get(f, "max_force"));
            vec3(f, "workspace_min", x.workspace_min, 3); vec3(f, "workspace_max", x.workspace_max, 3);
            x.rate_hz = j_num(j_get(f, "rate_hz"));
            x.timeout_ms = (uint16_t)j_u64(j_get(f, "timeout_ms")); x.caps = (uint16_t)j_u64(j_get(f, "caps"));
            j_str(j_get(f, "model"), x.model, sizeof x.model);
            j_hex(j_get(f, "cookie_hex"), x.cookie, PF_COOKIE_LEN);
            n = pf_encode_hello(out, sizeof out, key, kn, dev, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && !memcmp(&m.hello.nonce, x.nonce, 16) && m.hello.max_force == x.max_force &&
                   !strcmp(m.hello.model, x.model) && m.hello.caps == x.caps &&
                   !memcmp(m.hello.cookie, x.cookie, PF_COOKIE_LEN), "%s: decode", name);
        } else if (!strcmp(type, "COOKIE")) {
            pf_cookie x;
            j_hex(j_get(f, "client_nonce_hex"), x.client_nonce, 16); j_hex(j_get(f, "cookie_hex"), x.cookie, PF_COOKIE_LEN);
            n = pf_encode_cookie(out, sizeof out, key, kn, dev, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && !memcmp(m.cookie.cookie, x.cookie, PF_COOKIE_LEN), "%s: decode", name);
        } else if (!strcmp(type, "WELCOME")) {
            pf_welcome x; memset(&x, 0, sizeof x);
            j_hex(j_get(f, "client_nonce_hex"), x.client_nonce, 16); j_hex(j_get(f, "server_nonce_hex"), x.server_nonce, 16);
            x.slot = (uint16_t)j_u64(j_get(f, "slot")); x.timeout_ms = (uint16_t)j_u64(j_get(f, "timeout_ms"));
            x.rate_hz = j_num(j_get(f, "rate_hz")); x.max_force = j_num(j_get(f, "max_force"));
            x.t_service_ns = j_u64(j_get(f, "t_service_ns"));
            n = pf_encode_welcome(out, sizeof out, key, kn, dev, sess, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && m.welcome.t_service_ns == x.t_service_ns && h.session == sess, "%s: decode", name);
        } else if (!strcmp(type, "REJECT")) {
            pf_reject x;
            j_hex(j_get(f, "client_nonce_hex"), x.client_nonce, 16); x.error = (uint16_t)j_u64(j_get(f, "error"));
            n = pf_encode_reject(out, sizeof out, key, kn, dev, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && m.reject.error == x.error, "%s: decode", name);
        } else if (!strcmp(type, "STATE")) {
            pf_state x; memset(&x, 0, sizeof x);
            x.t_client_ns = j_u64(j_get(f, "t_client_ns")); x.t_echo_ns = j_u64(j_get(f, "t_echo_ns"));
            vec3(f, "position", x.position, 3); vec3(f, "increment", x.increment, 3); vec3(f, "orientation", x.orientation, 4);
            x.grasp = j_num(j_get(f, "grasp")); x.buttons = (uint32_t)j_u64(j_get(f, "buttons"));
            x.flags = (uint16_t)j_u64(j_get(f, "flags"));
            n = pf_encode_state(out, sizeof out, key, kn, dev, sess, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && h.seq == seq && m.state.t_client_ns == x.t_client_ns && m.state.buttons == x.buttons &&
                   !memcmp(m.state.position, x.position, sizeof x.position), "%s: decode (%s)", name, pf_error_name(e));
        } else if (!strcmp(type, "FEEDBACK")) {
            pf_feedback x; memset(&x, 0, sizeof x);
            x.tick = j_u64(j_get(f, "tick")); x.t_tick_ns = j_u64(j_get(f, "t_tick_ns")); x.t_sent_ns = j_u64(j_get(f, "t_sent_ns"));
            x.echo_seq = j_u64(j_get(f, "echo_seq")); x.echo_t_client_ns = j_u64(j_get(f, "echo_t_client_ns"));
            vec3(f, "force", x.force, 3); vec3(f, "proxy", x.proxy, 3); vec3(f, "robot", x.robot, 3);
            x.contact = (uint8_t)j_u64(j_get(f, "contact")); x.fixture = (uint8_t)j_u64(j_get(f, "fixture"));
            x.robot_mode = (uint8_t)j_u64(j_get(f, "robot_mode")); x.link = (uint8_t)j_u64(j_get(f, "link"));
            x.hold = (uint32_t)j_u64(j_get(f, "hold")); x.error = (uint16_t)j_u64(j_get(f, "error"));
            x.slot = (uint16_t)j_u64(j_get(f, "slot")); x.rejected = (uint32_t)j_u64(j_get(f, "rejected"));
            n = pf_encode_feedback(out, sizeof out, key, kn, dev, sess, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && m.feedback.echo_seq == x.echo_seq && m.feedback.rejected == x.rejected &&
                   !memcmp(m.feedback.force, x.force, sizeof x.force), "%s: decode", name);
        } else if (!strcmp(type, "BYE")) {
            pf_bye x; x.reason = (uint16_t)j_u64(j_get(f, "reason"));
            n = pf_encode_bye(out, sizeof out, key, kn, dev, sess, seq, &x);
            e = pf_decode(want, wn, key, kn, NULL, NULL, &h, &m);
            EXPECT(e == PF_OK && m.bye.reason == x.reason, "%s: decode", name);
        }
        hexstr(out, n, got_hex); hexstr(want, wn, want_hex);
        EXPECT(n == wn && n == (size_t)j_u64(j_get(v, "size")) && !memcmp(out, want, n),
               "%s: encoded bytes differ\n got  %s\n want %s", name, got_hex, want_hex);
    }
}

static void test_rejects(void) {
    int root = j_load(path("rejects.json")), vs = j_get(root, "vectors"), i;
    for (i = 0; i < j_count(vs); i++) {
        int v = j_at(vs, i);
        uint8_t buf[PF_MAX_DATAGRAM], key[64];
        double lo[3], hi[3];
        char name[64];
        size_t n = j_hex(j_get(v, "bytes_hex"), buf, sizeof buf), kn = j_hex(j_get(v, "key_hex"), key, sizeof key);
        int ws = j_bool(j_get(v, "use_workspace")), want = (int)j_u64(j_get(v, "code")), e;
        pf_header h; pf_message m;
        vec3(v, "workspace_min", lo, 3); vec3(v, "workspace_max", hi, 3);
        j_str(j_get(v, "name"), name, sizeof name);
        e = pf_decode(buf, n, key, kn, ws ? lo : NULL, ws ? hi : NULL, &h, &m);
        EXPECT(e == want, "reject %s: got %s, want %s", name, pf_error_name(e), pf_error_name(want));
    }
}

static void test_replay(void) {
    int root = j_load(path("replay.json")), ss = j_get(root, "streams"), i, k;
    for (i = 0; i < j_count(ss); i++) {
        int s = j_at(ss, i), seqs = j_get(s, "sequence"), res = j_get(s, "result");
        pf_window w; memset(&w, 0, sizeof w);
        for (k = 0; k < j_count(seqs); k++) {
            uint64_t q = j_u64(j_at(seqs, k));
            char want[16]; const char *got;
            int e = pf_window_check(&w, q);
            j_str(j_at(res, k), want, sizeof want);
            got = e ? pf_error_name(e) : (pf_window_commit(&w, q) ? "new" : "late");
            EXPECT(!strcmp(got, want), "replay stream %d item %d: got %s want %s", i, k, got, want);
        }
    }
}

/* keyfiles.json: the same table the Python loader runs (contents + mode -> key or refusal class) */
static void test_keyfiles(void) {
    int root = j_load(path("keyfiles.json")), cases = j_get(root, "cases"), i;
    char tmpl[] = "/tmp/pf-keyfile-XXXXXX";
    int fd = mkstemp(tmpl);
    EXPECT(fd >= 0, "mkstemp");
    if (fd < 0) return;
    close(fd);
    for (i = 0; i < j_count(cases); i++) {
        int c = j_at(cases, i), e, want;
        uint8_t content[512], key[PF_KEY_MAX], wantkey[PF_KEY_MAX];
        size_t cn = j_hex(j_get(c, "content_hex"), content, sizeof content), kn = 0, wn;
        char name[64], result[16];
        FILE *f;
        j_str(j_get(c, "name"), name, sizeof name);
        j_str(j_get(c, "result"), result, sizeof result);
        want = !strcmp(result, "ok") ? PF_OK : !strcmp(result, "mode") ? PF_E_KEY_MODE
             : !strcmp(result, "zero") ? PF_E_KEY_ZERO : PF_E_KEY_FORMAT;
        chmod(tmpl, 0600);
        f = fopen(tmpl, "wb");
        if (!f) { EXPECT(0, "keyfile %s: cannot write", name); continue; }
        if (cn) fwrite(content, 1, cn, f);
        fclose(f);
        chmod(tmpl, (mode_t)j_u64(j_get(c, "mode")));
        e = pf_load_key(tmpl, key, sizeof key, &kn);
        EXPECT(e == want, "keyfile %s: got %s, want %s", name, pf_error_name(e), pf_error_name(want));
        if (e == PF_OK && want == PF_OK) {
            wn = j_hex(j_get(c, "key_hex"), wantkey, sizeof wantkey);
            EXPECT(kn == wn && !memcmp(key, wantkey, wn), "keyfile %s: key differs", name);
        }
    }
    unlink(tmpl);
}

int main(int argc, char **argv) {
    snprintf(dir, sizeof dir, "%s", argc > 1 ? argv[1] : "clients/vectors");
    test_sha256();
    test_hmac();
    test_session_keys();
    test_messages();
    test_rejects();
    test_replay();
    test_keyfiles();
    free(j_text);
    printf("%d checks, %d failures\n", checks, failures);
    return failures ? 1 : 0;
}
