/*
 * pointfence client SDK (C99, libc + POSIX sockets only).
 *
 * A haptic device (OpenHaptics, Force Dimension dhd, libnifalcon, ...) becomes a master of a
 * pointfence service: open a client, connect (HELLO/WELCOME handshake with the pre-shared key),
 * then once per device tick send the device state and read the force to display.
 * The wire protocol is specified in clients/PROTOCOL.md; clients/vectors/ holds the test
 * vectors this library reproduces byte for byte.
 *
 *   pf_client c;  pf_hello caps = pf_hello_defaults();
 *   pf_client_open(&c, "127.0.0.1", 47800, key, key_len, 7, &caps);
 *   pf_client_connect(&c, 5000);
 *   for (;;) {                                   // your 1 kHz device loop
 *       pf_state s = pf_state_defaults();
 *       read_device(s.position);                 // driver: position read (m, master frame)
 *       pf_client_send_state(&c, &s);
 *       pf_client_poll(&c);
 *       double f[3]; pf_client_force(&c, f);     // zero when the link is stale
 *       write_device_force(f);                   // driver: force write (N, master frame)
 *   }
 *   pf_client_close(&c);
 *
 * Every function returns PF_OK (0) or a PF_E_* code unless stated otherwise. Nothing allocates.
 * Licence: BSD-3-Clause (the pointfence licence); SHA-256 and HMAC are implemented in
 * pf_sha256.c from FIPS 180-4 and RFC 2104 (no third-party code).
 */
#ifndef POINTFENCE_CLIENT_H
#define POINTFENCE_CLIENT_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define PF_PROTOCOL_VERSION 2
#define PF_HEADER_LEN 24
#define PF_TAG_LEN 16
#define PF_NONCE_LEN 16
#define PF_COOKIE_LEN 24
#define PF_KEY_MAX 64
#define PF_MAX_DATAGRAM 2048
#define PF_WINDOW 64
#define PF_DEFAULT_TIMEOUT_MS 50

/* message types and their fixed sizes (bytes, tag included) */
enum pf_type { PF_HELLO = 1, PF_WELCOME = 2, PF_REJECT = 3, PF_STATE = 4, PF_FEEDBACK = 5, PF_BYE = 6, PF_COOKIE = 7 };
enum pf_size {
    PF_HELLO_SIZE = 168, PF_WELCOME_SIZE = 104, PF_REJECT_SIZE = 64,
    PF_STATE_SIZE = 152, PF_FEEDBACK_SIZE = 172, PF_BYE_SIZE = 48, PF_COOKIE_SIZE = 80
};

/* error codes (identical to the protocol's; >= 100: local errors of this library) */
enum pf_error {
    PF_OK = 0, PF_E_MALFORMED = 1, PF_E_VERSION = 2, PF_E_TRUNCATED = 3, PF_E_OVERSIZED = 4,
    PF_E_AUTH = 5, PF_E_REPLAY = 6, PF_E_STALE = 7, PF_E_NO_SESSION = 8, PF_E_NON_FINITE = 9,
    PF_E_WORKSPACE = 10, PF_E_FULL = 11, PF_E_BUSY = 12, PF_E_TIMEOUT = 13, PF_E_CAPABILITY = 14,
    PF_E_DIRECTION = 15, PF_E_COOKIE = 16,
    PF_E_ARGUMENT = 100,   /* bad argument (NULL, buffer too small, key length) */
    PF_E_SYSTEM = 101,     /* socket or clock error (see errno) */
    PF_E_NOT_CONNECTED = 102,
    PF_E_LINK_LOST = 103,  /* no feedback for longer than the session timeout */
    PF_E_KEY_MODE = 104,   /* key file readable or writable by group or others: chmod 600 FILE */
    PF_E_KEY_FORMAT = 105, /* key file is not 32..128 hex digits and at most one newline (PROTOCOL.md 3.1) */
    PF_E_KEY_ZERO = 106    /* key file holds an all-zero key: write a random one (pointfence serve --new-key) */
};

/* HELLO capability bits, STATE flags, FEEDBACK fields */
#define PF_CAP_FORCE 0x1u
#define PF_CAP_ORIENTATION 0x2u
#define PF_CAP_GRASP 0x4u
#define PF_CAP_CLUTCH 0x8u
#define PF_F_CLUTCH 0x1u
#define PF_F_ORIENTATION 0x2u
#define PF_F_GRASP 0x4u
#define PF_FX_HAPTICS 0x1u
#define PF_FX_TELEOP 0x2u
#define PF_FX_COUPLED 0x4u
#define PF_FX_FIXTURE 0x8u
enum pf_robot_mode { PF_ROBOT_IDEAL = 0, PF_ROBOT_ENABLED = 1, PF_ROBOT_HOLDING = 2, PF_ROBOT_FAULT = 3 };
enum pf_contact { PF_CONTACT_FREE = 0, PF_CONTACT_CONTACT = 1, PF_CONTACT_ENTRENCHED = 2 };

typedef struct { uint8_t type; uint32_t device_id; uint32_t session; uint64_t seq; } pf_header;

typedef struct {
    uint8_t nonce[PF_NONCE_LEN];
    double max_force;                       /* N */
    double workspace_min[3], workspace_max[3]; /* m, master frame */
    double rate_hz;
    uint16_t timeout_ms;                    /* 0: the service default */
    uint16_t caps;                          /* PF_CAP_* */
    char model[17];                         /* printable ASCII, NUL-terminated */
    uint8_t cookie[PF_COOKIE_LEN];          /* zeros in the first HELLO; the service's COOKIE in the second */
} pf_hello;

typedef struct { uint8_t client_nonce[PF_NONCE_LEN], cookie[PF_COOKIE_LEN]; } pf_cookie;

typedef struct {
    uint8_t client_nonce[PF_NONCE_LEN], server_nonce[PF_NONCE_LEN];
    uint16_t slot, timeout_ms;
    double rate_hz, max_force;
    uint64_t t_service_ns;
} pf_welcome;

typedef struct { uint8_t client_nonce[PF_NONCE_LEN]; uint16_t error; } pf_reject;

typedef struct {
    uint64_t t_client_ns, t_echo_ns;
    double position[3], increment[3];       /* m, master frame */
    double orientation[4];                  /* quaternion w, x, y, z */
    double grasp;
    uint32_t buttons;
    uint16_t flags;                         /* PF_F_* */
} pf_state;

typedef struct {
    uint64_t tick, t_tick_ns, t_sent_ns, echo_seq, echo_t_client_ns;
    double force[3];                        /* N, master frame */
    double proxy[3], robot[3];              /* m, world frame */
    uint8_t contact, fixture, robot_mode, link;
    uint32_t hold;
    uint16_t error, slot;
    uint32_t rejected;
} pf_feedback;

typedef struct { uint16_t reason; } pf_bye;

/* ---- SHA-256, HMAC-SHA256, session key ---- */
typedef struct { uint32_t h[8]; uint64_t len; uint8_t buf[64]; size_t n; } pf_sha256_ctx;
void pf_sha256_init(pf_sha256_ctx *c);
void pf_sha256_update(pf_sha256_ctx *c, const void *data, size_t len);
void pf_sha256_final(pf_sha256_ctx *c, uint8_t out[32]);
void pf_sha256(const void *data, size_t len, uint8_t out[32]);
void pf_hmac_sha256(const uint8_t *key, size_t key_len, const void *data, size_t len, uint8_t out[32]);
void pf_session_key(const uint8_t *psk, size_t psk_len, const uint8_t client_nonce[16],
                    const uint8_t server_nonce[16], uint32_t device_id, uint32_t session, uint8_t out[32]);

/* ---- codec: encode returns the size written (0 on a bad argument) ---- */
pf_hello pf_hello_defaults(void);
pf_state pf_state_defaults(void);
size_t pf_encode_hello(uint8_t *out, size_t cap, const uint8_t *psk, size_t psk_len, uint32_t device_id,
                       uint64_t seq, const pf_hello *m);
size_t pf_encode_welcome(uint8_t *out, size_t cap, const uint8_t *psk, size_t psk_len, uint32_t device_id,
                         uint32_t session, uint64_t seq, const pf_welcome *m);
size_t pf_encode_reject(uint8_t *out, size_t cap, const uint8_t *psk, size_t psk_len, uint32_t device_id,
                        uint64_t seq, const pf_reject *m);
size_t pf_encode_state(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t device_id,
                       uint32_t session, uint64_t seq, const pf_state *m);
size_t pf_encode_feedback(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t device_id,
                          uint32_t session, uint64_t seq, const pf_feedback *m);
size_t pf_encode_bye(uint8_t *out, size_t cap, const uint8_t *key, size_t key_len, uint32_t device_id,
                     uint32_t session, uint64_t seq, const pf_bye *m);
size_t pf_encode_cookie(uint8_t *out, size_t cap, const uint8_t *psk, size_t psk_len, uint32_t device_id,
                        uint64_t seq, const pf_cookie *m);

/* decoding: size/magic/version/type, then the tag, then the values (in this order) */
int pf_parse_header(const uint8_t *buf, size_t len, pf_header *h);
int pf_verify(const uint8_t *buf, size_t len, const uint8_t *key, size_t key_len);
int pf_decode_hello(const uint8_t *buf, size_t len, pf_hello *m);
int pf_decode_welcome(const uint8_t *buf, size_t len, pf_welcome *m);
int pf_decode_reject(const uint8_t *buf, size_t len, pf_reject *m);
/* ws_min/ws_max: the workspace declared at HELLO (NULL: only the 10 m bound) */
int pf_decode_state(const uint8_t *buf, size_t len, const double *ws_min, const double *ws_max, pf_state *m);
int pf_decode_feedback(const uint8_t *buf, size_t len, pf_feedback *m);
int pf_decode_bye(const uint8_t *buf, size_t len, pf_bye *m);
int pf_decode_cookie(const uint8_t *buf, size_t len, pf_cookie *m);

typedef union { pf_hello hello; pf_welcome welcome; pf_reject reject; pf_state state; pf_feedback feedback; pf_bye bye;
                pf_cookie cookie; } pf_message;
/* all three steps with one key */
int pf_decode(const uint8_t *buf, size_t len, const uint8_t *key, size_t key_len, const double *ws_min,
              const double *ws_max, pf_header *h, pf_message *m);

/* ---- replay window (64 sequences) ---- */
typedef struct { uint64_t top, bits; } pf_window;
int pf_window_check(const pf_window *w, uint64_t seq);        /* PF_OK, PF_E_REPLAY or PF_E_STALE */
int pf_window_commit(pf_window *w, uint64_t seq);             /* 1: newest so far, 0: late */

/* ---- client ---- */
typedef struct {
    int fd;
    uint8_t psk[PF_KEY_MAX]; size_t psk_len;
    uint32_t device_id, session;
    uint8_t key[32];
    pf_hello hello;
    pf_welcome welcome;
    pf_window window;
    uint64_t seq, hellos;
    uint64_t last_rx_ns, timeout_ns;
    uint64_t off_ns; int have_off;          /* min(receive - sent): phase lock */
    int has_prev; double prev[3];
    int has_feedback; pf_feedback feedback;
    double force[3];
    uint32_t rejected_in;                   /* datagrams this client dropped */
    uint64_t sent, received;
} pf_client;

uint64_t pf_now_ns(void);                                     /* CLOCK_MONOTONIC, ns */
const char *pf_error_name(int code);
/* Key files (PROTOCOL.md 3.1): 32..128 hex digits, at most one "\n" or "\r\n", nothing else; not all
 * zero; mode 0600 or stricter. PF_E_SYSTEM (cannot open: see errno), PF_E_KEY_MODE, PF_E_KEY_FORMAT,
 * PF_E_KEY_ZERO, PF_E_ARGUMENT (cap below the key). pf_parse_key checks the contents alone. */
int pf_load_key(const char *path, uint8_t *key, size_t cap, size_t *len);
int pf_parse_key(const uint8_t *text, size_t n, uint8_t *key, size_t cap, size_t *len);
int pf_client_open(pf_client *c, const char *host, uint16_t port, const uint8_t *psk, size_t psk_len,
                   uint32_t device_id, const pf_hello *caps);
int pf_client_connect(pf_client *c, int timeout_ms);          /* PF_OK, PF_E_TIMEOUT, a REJECT's code */
int pf_client_send_state(pf_client *c, pf_state *s);          /* fills t_client_ns if 0, t_echo_ns, increment */
int pf_client_poll(pf_client *c);                             /* >= 0: new feedback messages; < 0: -code */
int pf_client_force(const pf_client *c, double f[3]);         /* 1: fresh; 0: stale (f zeroed) */
int pf_client_fresh(const pf_client *c);
/* the first service tick deadline after `after_ns` (client clock); 0 when not known yet */
uint64_t pf_client_next_tick_ns(const pf_client *c, uint64_t after_ns);
void pf_client_close(pf_client *c);

#ifdef __cplusplus
}
#endif
#endif
