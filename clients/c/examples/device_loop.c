/* A haptic device loop on the pointfence C SDK.
 *
 *   device_loop HOST PORT KEYFILE [DEVICE_ID] [SECONDS]
 *
 * The device here is simulated (a slow circle); the two places marked DRIVER are where a real
 * driver's calls go, e.g.
 *   OpenHaptics (Phantom Omni / Geomagic Touch), inside an hdScheduleAsynchronous callback:
 *       hdGetDoublev(HD_CURRENT_POSITION, p);   // mm: multiply by 1e-3
 *       hdSetDoublev(HD_CURRENT_FORCE, f);
 *   Force Dimension (dhd):  dhdGetPosition(&x, &y, &z);   dhdSetForceAndTorque(fx, fy, fz, 0, 0, 0);
 *   libnifalcon:            falcon.getPosition();  falcon.setForce(f);  (C++, same places)
 * The device's own servo loop (1 kHz) calls one_tick(); this example runs its own 1 kHz loop,
 * phase-locked to the service's ticks so that each sample arrives just before the tick using it.
 */
#ifndef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L
#endif
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "pointfence_client.h"

#define LEAD_NS 250000u       /* send this long before the service's tick */

static void read_device_position(double t, double p[3], int *pedal) {
    /* DRIVER: position read (m, device frame = master frame) and the clutch pedal */
    p[0] = 0.02 * cos(2.0 * 3.14159265358979 * 0.25 * t);
    p[1] = 0.02 * sin(2.0 * 3.14159265358979 * 0.25 * t);
    p[2] = -0.01 * t;
    *pedal = 1;
}

static void write_device_force(const double f[3]) {
    /* DRIVER: force write (N, master frame). The SDK gives zero when the link is stale. */
    (void)f;
}

static void sleep_until(uint64_t t_ns) {
    uint64_t now = pf_now_ns();
    if (t_ns > now + 200000u) {
        struct timespec ts;
        uint64_t d = t_ns - now - 200000u;
        ts.tv_sec = (time_t)(d / 1000000000u); ts.tv_nsec = (long)(d % 1000000000u);
        nanosleep(&ts, NULL);
    }
    while (pf_now_ns() < t_ns) { }
}

int main(int argc, char **argv) {
    uint8_t key[PF_KEY_MAX];
    size_t key_len;
    pf_client c;
    pf_hello caps = pf_hello_defaults();
    uint64_t t0, deadline, period = 1000000u, ticks = 0, fresh = 0;
    double seconds, fmax = 0;
    int e;
    if (argc < 4) {
        fprintf(stderr, "usage: %s HOST PORT KEYFILE [DEVICE_ID] [SECONDS]\n", argv[0]);
        return 2;
    }
    seconds = argc > 5 ? atof(argv[5]) : 5.0;
    e = pf_load_key(argv[3], key, sizeof key, &key_len);
    if (e) {
        fprintf(stderr, "key file %s refused (%s): %s\n", argv[3], pf_error_name(e),
                e == PF_E_KEY_MODE ? "others may read it; run chmod 600 on it"
                : e == PF_E_KEY_ZERO ? "an all-zero key; write a random one with pointfence serve --new-key FILE"
                : e == PF_E_KEY_FORMAT ? "expected 32 to 128 hex digits and at most one newline (pointfence serve --new-key FILE)"
                : "cannot open it");
        return 1;
    }
    caps.max_force = 3.3;                         /* the device's limits */
    caps.workspace_min[0] = caps.workspace_min[1] = caps.workspace_min[2] = -0.08;
    caps.workspace_max[0] = caps.workspace_max[1] = caps.workspace_max[2] = 0.08;
    if ((e = pf_client_open(&c, argv[1], (uint16_t)atoi(argv[2]), key, key_len,
                            argc > 4 ? (uint32_t)strtoul(argv[4], NULL, 10) : 1u, &caps))) {
        fprintf(stderr, "open: %s\n", pf_error_name(e)); return 1;
    }
    if ((e = pf_client_connect(&c, 10000))) { fprintf(stderr, "connect: %s\n", pf_error_name(e)); return 1; }
    printf("session %u on slot %u, timeout %u ms\n", c.session, c.welcome.slot, c.welcome.timeout_ms);
    t0 = deadline = pf_now_ns();
    while (pf_now_ns() - t0 < (uint64_t)(seconds * 1e9)) {
        pf_state s = pf_state_defaults();
        double f[3];
        int pedal, r;
        uint64_t g;
        sleep_until(deadline);
        r = pf_client_poll(&c);                   /* newest force from the service */
        if (r < 0) { fprintf(stderr, "link: %s\n", pf_error_name(-r)); break; }
        fresh += (uint64_t)pf_client_force(&c, f);
        write_device_force(f);
        if (sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) > fmax) fmax = sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        read_device_position((double)(pf_now_ns() - t0) / 1e9, s.position, &pedal);
        s.flags = pedal ? PF_F_CLUTCH : 0;
        if (pf_client_send_state(&c, &s)) break;
        ticks++;
        g = pf_client_next_tick_ns(&c, deadline + period / 2 + LEAD_NS);   /* phase lock */
        deadline = g ? g - LEAD_NS : deadline + period;
    }
    printf("%llu ticks, %llu with fresh feedback, max force %.3f N, %u datagrams rejected\n",
           (unsigned long long)ticks, (unsigned long long)fresh, fmax, c.rejected_in);
    pf_client_close(&c);
    return 0;
}
