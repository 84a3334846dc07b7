// Fixed-radius neighbours in the spatial hash, shaped for GPUs: one work-group per query, its
// candidates spread over the work-items. Results are those of `neighbors` (neighbors.cl) and of
// kernels/reference/neighbors.py bit for bit; kernels/opencl/pipeline.py chooses between the two.
//
// Scan order: a query scans the rows (z, y) of its cells in turn, and each row's cells x0..x1
// are one contiguous range of the sorted points, so scan order is ascending sorted index. The
// rows are taken W at a time (a batch; one batch unless the reach spans more than W rows): work-
// item r lists row r's range, an inclusive scan of the lengths lays the batch's candidates end to
// end, and each work-item takes one contiguous run of them. It counts its hits, an exclusive
// scan of the counts tells it where in the result row its hits go, and while that is below K it
// writes them (the hits among the first 64 candidates of its run kept as bits from the count, the
// rest of a longer run tested again): the first K hits in scan order, however the work is split.
// Count and nearest need no order: each work-item keeps its own (squared distance, index)
// minimum, reduced over the work-group at the end, ties going to the smaller index (the
// reference's argmin takes the first). Squared distances are rounded after every operation in
// the reference's order (FP_CONTRACT OFF, no fused multiply-adds; the program is built with
// correctly rounded sqrt), so hits, nearest and distance are the reference's to the bit.
//
// Every barrier is reached by the whole work-group: the batch loop's trip count and the scans'
// depend only on the query and the work-group size, and no loop with a barrier is left early.
#pragma OPENCL FP_CONTRACT OFF

// Inclusive scan of v over the work-group (Hillis-Steele, double-buffered in buf[2 W]); *total
// gets the sum over the work-group. buf may be reused after the caller's next barrier.
inline int nb_scan(__local int *buf, int v, int *total) {
    const int lid = get_local_id(0), W = get_local_size(0);
    buf[lid] = v;
    barrier(CLK_LOCAL_MEM_FENCE);
    int pin = 0;
    for (int o = 1; o < W; o <<= 1) {
        int s = buf[pin * W + lid];
        if (lid >= o) s += buf[pin * W + lid - o];
        buf[(1 - pin) * W + lid] = s;
        pin = 1 - pin;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    *total = buf[pin * W + W - 1];
    return buf[pin * W + lid];
}

// Index of the lowest set bit of x (x != 0)
inline int nb_ctz64(ulong x) {
    return 63 - (int)clz(x & (~x + 1));
}

// Whether sorted point i is a neighbour of q (within radius in float32, protected where asked);
// *d2 gets its squared distance, m^2.
inline int nb_hit(__global const float4 *pts, __global const int *order, int i, float4 q, float r2,
                  int protected_only, float *d2) {
    int entry = order[i];
    if (protected_only && entry >= 0) return 0;
    float4 p = pts[entry & 0x7fffffff];
    float dx = p.x - q.x, dy = p.y - q.y, dz = p.z - q.z;
    *d2 = dx * dx + dy * dy + dz * dz;
    return *d2 <= r2;
}

// Query b (work-group b) into res: res[b] the count, res[nq + b] the nearest hit (-1 if none),
// res[2 nq + b] the bits of its distance (m, float32; inf if none), and from res[3 nq + b K] on
// the first min(count, K) hits in scan order, -1 after. Arguments as neighbors.cl's, then local
// memory sized by the host for W work-items: rowa[W] (first sorted index of each row of the
// batch), rowp[W + 1] (candidates of the batch before each row), scan[2 W] (the scans, then the
// nearest's reduction).
__kernel void neighbors_wg(__global const float4 *pts, __global const int *order, __global const int *start,
                           float4 grid, int4 dims, __global const float4 *queries, int nq,
                           float radius, int span, int K, int protected_only, __global int *res,
                           __local int *rowa, __local int *rowp, __local int *scan) {
    const int b = get_group_id(0), lid = get_local_id(0), W = get_local_size(0);
    float4 q = queries[b];
    int cx = (int)clamp(floor((q.x - grid.x) * grid.w), (float)(-span - 1), (float)(dims.x + span));
    int cy = (int)clamp(floor((q.y - grid.y) * grid.w), (float)(-span - 1), (float)(dims.y + span));
    int cz = (int)clamp(floor((q.z - grid.z) * grid.w), (float)(-span - 1), (float)(dims.z + span));
    int x0 = max(cx - span, 0), x1 = min(cx + span, dims.x - 1);
    int y0 = max(cy - span, 0), y1 = min(cy + span, dims.y - 1);
    int z0 = max(cz - span, 0), z1 = min(cz + span, dims.z - 1);
    int ny = y1 - y0 + 1, nz = z1 - z0 + 1;
    int nrows = (x0 <= x1 && ny > 0 && nz > 0) ? ny * nz : 0;
    float r2 = radius * radius;
    __global int *idx = res + 3 * nq + (size_t)b * K;
    int n = 0;                                      // hits of the batches before (work-group wide)
    int bestd = 0x7fffffff, besti = 0x7fffffff;     // this work-item's nearest: (d2 bits, index)
    int nbatch = (nrows + W - 1) / W;
    for (int rb = 0; rb < nbatch; ++rb) {
        int rr = rb * W + lid, a = 0, len = 0;
        if (rr < nrows) {
            int base = ((z0 + rr / ny) * dims.y + y0 + rr % ny) * dims.x;
            a = start[base + x0];
            len = start[base + x1 + 1] - a;
        }
        int total;
        int incl = nb_scan(scan, len, &total);
        rowa[lid] = a;
        rowp[lid + 1] = incl;
        if (lid == 0) rowp[0] = 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        // this work-item's run [k0, k1) of the batch's candidates; r0: the row holding k0
        int C = (total + W - 1) / W;
        int k0 = min(lid * C, total), k1 = min(k0 + C, total);
        int lo = 0, hi = W - 1;
        while (lo < hi) {                            // first row r with rowp[r + 1] > k0
            int mid = (lo + hi) >> 1;
            if (rowp[mid + 1] > k0) hi = mid; else lo = mid + 1;
        }
        int r0 = lo, cnt = 0;
        ulong hm = 0;                                // bit j: candidate k0 + j is a hit (j < 64)
        for (int r = r0; r < W && rowp[r] < k1; ++r) {
            int ia = rowa[r] - rowp[r], kb = min(k1, rowp[r + 1]);
            for (int k = max(k0, rowp[r]); k < kb; ++k) {
                float d2;
                if (nb_hit(pts, order, ia + k, q, r2, protected_only, &d2)) {
                    ++cnt;
                    if (k - k0 < 64) hm |= (ulong)1 << (k - k0);
                    int kd = as_int(d2);             // (d2 >= 0: its bits order as it does)
                    if (kd < bestd || (kd == bestd && ia + k < besti)) { bestd = kd; besti = ia + k; }
                }
            }
        }
        int hits;
        int at = n + nb_scan(scan, cnt, &hits) - cnt;
        if (cnt > 0 && at < K) {
            // write pass, this work-item's hits in scan order: the first 64 candidates of the run
            // from the bits, the rest (a run longer than 64) tested again
            int r = r0;
            while (hm != 0 && at < K) {
                int k = k0 + nb_ctz64(hm);
                hm &= hm - 1;
                while (rowp[r + 1] <= k) ++r;
                idx[at++] = rowa[r] - rowp[r] + k;
            }
            int kr = k0 + 64;
            for (; r < W && rowp[r] < k1 && at < K; ++r) {
                int ia = rowa[r] - rowp[r], kb = min(k1, rowp[r + 1]);
                for (int k = max(kr, rowp[r]); k < kb && at < K; ++k) {
                    float d2;
                    if (nb_hit(pts, order, ia + k, q, r2, protected_only, &d2)) idx[at++] = ia + k;
                }
            }
        }
        n += hits;
        barrier(CLK_LOCAL_MEM_FENCE);                // rowa, rowp and scan are reused by the next batch
    }
    // the work-group's smallest (d2 bits, index), lexicographically (scan is free: the batch
    // loop ends on a barrier)
    __local int *keyd = scan, *keyi = scan + W;
    keyd[lid] = bestd;
    keyi[lid] = besti;
    barrier(CLK_LOCAL_MEM_FENCE);
    int p2 = 1;   // W rounded up to a power of two
    while (p2 < W) p2 <<= 1;
    for (int s = p2 >> 1; s > 0; s >>= 1) {
        if (lid < s && lid + s < W) {
            int d = keyd[lid + s], i = keyi[lid + s];
            if (d < keyd[lid] || (d == keyd[lid] && i < keyi[lid])) { keyd[lid] = d; keyi[lid] = i; }
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    for (int j = n + lid; j < K; j += W) idx[j] = -1;
    if (lid == 0) {
        res[b] = n;
        res[nq + b] = n > 0 ? keyi[0] : -1;
        res[2 * nq + b] = as_int(n > 0 ? sqrt(as_float(keyd[0])) : INFINITY);
    }
}
