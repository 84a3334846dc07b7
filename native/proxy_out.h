/* The OpenCL proxy kernels' packed output, unpacked into the batch's arrays (kernels/proxy.py,
 * kernels/opencl/proxy.py).
 *
 * The kernel (proxy.cl, proxy_gpu.cl) writes one row of 8 float32 per proxy: the position (world, m),
 * the distance to the nearest point (m), the contact normal, and, in the last float's bits, an
 * int32 of the contact state (bits 0-1), the converged flag (bit 2) and the steps taken (bits 3
 * and up). Included by tick_core.c (one library). */
#ifndef PF_PROXY_OUT_H
#define PF_PROXY_OUT_H

#include <stdint.h>
#include <string.h>

void pf_proxy_unpack(const float *out, int64_t n, float *pos, float *nearest, float *normals, int32_t *states,
                     int32_t *steps, uint8_t *converged) {
    for (int64_t i = 0; i < n; i++) {
        const float *o = out + 8 * i;
        int32_t info;
        memcpy(&info, o + 7, sizeof info);
        pos[3 * i] = o[0];
        pos[3 * i + 1] = o[1];
        pos[3 * i + 2] = o[2];
        nearest[i] = o[3];
        normals[3 * i] = o[4];
        normals[3 * i + 1] = o[5];
        normals[3 * i + 2] = o[6];
        states[i] = info & 3;
        steps[i] = info >> 3;              /* (info is never negative: steps fit in 28 bits) */
        converged[i] = (uint8_t)((info & 4) != 0);
    }
}

#endif
