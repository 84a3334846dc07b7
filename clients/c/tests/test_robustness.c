/* Parser robustness: random and mutated datagrams never crash the decoder, never decode as a
 * valid message unless authentic, and a mutated authentic datagram never verifies. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "pointfence_client.h"

static uint64_t rng = 0x9E3779B97F4A7C15u;
static uint64_t next(void) { rng ^= rng << 13; rng ^= rng >> 7; rng ^= rng << 17; return rng; }

int main(int argc, char **argv) {
    long iters = argc > 1 ? atol(argv[1]) : 200000, i, accepted_random = 0, forged = 0, ok_mut = 0;
    uint8_t key[32], other[32], base[7][PF_MAX_DATAGRAM], buf[PF_MAX_DATAGRAM + 64];
    size_t blen[7];
    double lo[3] = {-0.1, -0.1, -0.1}, hi[3] = {0.1, 0.1, 0.1};
    long counts[128];
    int k;
    pf_hello he = pf_hello_defaults(); pf_welcome we; pf_reject re; pf_state st = pf_state_defaults();
    pf_feedback fb; pf_bye by; pf_cookie ck;
    memset(counts, 0, sizeof counts);
    for (k = 0; k < 32; k++) { key[k] = (uint8_t)(k * 7 + 1); other[k] = (uint8_t)(k * 7 + 2); }
    memset(&we, 0, sizeof we); we.timeout_ms = 50; we.rate_hz = 1000; we.max_force = 3;
    memset(&re, 0, sizeof re); memset(&fb, 0, sizeof fb); by.reason = 0;
    st.position[0] = 0.01;
    blen[0] = pf_encode_hello(base[0], PF_MAX_DATAGRAM, key, 32, 5, 1, &he);
    blen[1] = pf_encode_welcome(base[1], PF_MAX_DATAGRAM, key, 32, 5, 9, 0, &we);
    blen[2] = pf_encode_reject(base[2], PF_MAX_DATAGRAM, key, 32, 5, 0, &re);
    blen[3] = pf_encode_state(base[3], PF_MAX_DATAGRAM, key, 32, 5, 9, 3, &st);
    blen[4] = pf_encode_feedback(base[4], PF_MAX_DATAGRAM, key, 32, 5, 9, 3, &fb);
    blen[5] = pf_encode_bye(base[5], PF_MAX_DATAGRAM, key, 32, 5, 9, 4, &by);
    for (k = 0; k < 16; k++) ck.client_nonce[k] = (uint8_t)k;
    for (k = 0; k < PF_COOKIE_LEN; k++) ck.cookie[k] = (uint8_t)(0xA0 + k);
    blen[6] = pf_encode_cookie(base[6], PF_MAX_DATAGRAM, key, 32, 5, 0, &ck);
    for (k = 0; k < 7; k++) {
        pf_header h; pf_message m;
        if (pf_decode(base[k], blen[k], key, 32, lo, hi, &h, &m) != PF_OK) { fprintf(stderr, "base %d invalid\n", k); return 1; }
    }
    for (i = 0; i < iters; i++) {
        pf_header h; pf_message m;
        size_t n;
        int e, mode = (int)(next() % 4);
        int b = (int)(next() % 7);
        if (mode == 0) {             /* random bytes, random length (sometimes a valid header) */
            size_t j;
            int typ = (int)(1 + next() % 7);
            n = next() % 2 ? blen[typ - 1] : (size_t)(next() % 300);   /* often exactly a message size */
            for (j = 0; j < n; j++) buf[j] = (uint8_t)next();
            if (n >= 24 && next() % 2) { buf[0] = 'P'; buf[1] = 'F'; buf[2] = PF_PROTOCOL_VERSION; buf[3] = (uint8_t)typ; memset(buf + 20, 0, 4); }
            e = pf_decode(buf, n, key, 32, lo, hi, &h, &m);
            if (e == PF_OK) accepted_random++;
        } else {                      /* mutate an authentic datagram */
            int flips = 1 + (int)(next() % 4), f;
            memcpy(buf, base[b], blen[b]);
            n = blen[b];
            for (f = 0; f < flips; f++) {
                int what = (int)(next() % 5);
                if (n < 24 && what != 3) continue;
                if (what == 0) buf[next() % n] ^= (uint8_t)(1u << (next() % 8));
                else if (what == 1) buf[next() % n] = (uint8_t)next();
                else if (what == 2 && n > 1) n = (size_t)(next() % n);
                else if (what == 3) { size_t add = 1 + next() % 40, j; for (j = 0; j < add; j++) buf[n + j] = (uint8_t)next(); n += add; }
                else buf[12 + next() % 8] = (uint8_t)next();   /* sequence bytes */
            }
            if (n > PF_MAX_DATAGRAM) n = PF_MAX_DATAGRAM;
            e = pf_decode(buf, n, mode == 3 ? other : key, 32, lo, hi, &h, &m);
            if (e == PF_OK) {
                if (n == blen[b] && !memcmp(buf, base[b], n) && mode != 3) ok_mut++;   /* mutation undone itself */
                else forged++;
            }
        }
        counts[e < 128 && e >= 0 ? e : 127]++;
    }
    printf("%ld datagrams: accepted random %ld, forged accepted %ld, unchanged %ld\n", iters, accepted_random, forged, ok_mut);
    for (k = 0; k <= PF_E_COOKIE; k++) if (counts[k]) printf("  %-12s %ld\n", pf_error_name(k), counts[k]);
    return (accepted_random || forged) ? 1 : 0;
}
