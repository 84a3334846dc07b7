/* The Warp neighbour query's index rows (kernels/warp/pipeline.py, WarpPipeline._neighbors).
 *
 * The query kernel writes each query's first min(count, K) hits at the start of its row of K in
 * the result buffer and nothing after them; this copies those hits into the caller's (B, K)
 * index array and pads each row with -1, reading only the hits (most of a row of K is usually
 * empty). Included by tick_core.c (one library). */
#ifndef PF_NEIGHBOR_ROWS_H
#define PF_NEIGHBOR_ROWS_H

#include <stdint.h>
#include <string.h>

void pf_neighbor_rows(const int32_t *rows, const int32_t *count, int64_t n_queries, int64_t k, int32_t *index) {
    for (int64_t b = 0; b < n_queries; b++) {
        int64_t c = count[b];
        if (c < 0) c = 0;
        if (c > k) c = k;
        const int32_t *src = rows + b * k;
        int32_t *dst = index + b * k;
        memcpy(dst, src, (size_t)c * sizeof *dst);
        for (int64_t j = c; j < k; j++) dst[j] = -1;
    }
}

#endif
