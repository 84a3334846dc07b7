// Batched proxy movement of one haptic tick, shaped for GPUs: one work-group per proxy, its
// working set in local memory (the model is the Warp kernel, kernels/warp/tick_kernels.py).
// Built after proxy.cl, whose helpers it uses (point_at, cell_range, the direct hash paths,
// state_of, normal_of); kernels/opencl/proxy.py chooses between the two kernels.
//
// The decisions and results are those of proxy_tick (proxy.cl) and of the NumPy reference, bit
// for bit:
// * the working set holds the same points in the same order (the hash's cell order): the
//   gather gives each work-item a contiguous run of the candidates, counts its points, and an
//   exclusive scan of the counts tells each work-item where its points go;
// * the normal sums are taken in the CPU kernel's order: point k of the set goes to lane k % 8,
//   each lane adds its points in order and the 8 lanes are added 0..7. The work-group computes
//   every point's contribution in parallel into a term buffer in local memory (tb points at a
//   time), and 24 work-items (3 components x 8 lanes) add them in that order;
// * minima (the smallest clearance, the clip's hit time) do not depend on the order: one local
//   atomic minimum per work-item over float bits mapped to ordered integers;
// * the clip scans the points with clearance below rclip (proxy_tick lists the 8-point chunks
//   holding one: a superset, and no other point can shorten a step), each work-item its own,
//   kept as bits of a register (bit i: the work-item's i-th point, lid + i * W; cap <= 64 W).
// Sets with more than cap points take the direct hash path of proxy.cl, every work-item of the
// group running it in step (same result in every work-item).
#pragma OPENCL FP_CONTRACT OFF

#define GW_ROWS 128     // hash rows (z, y) a parallel gather lists; more: one work-item gathers
#define GW_MAXW 256     // largest work-group (the scan's buffer)
#define GW_NONE 0x7fffffff

// float -> int with the same order (for atomic_min); its own inverse
inline int fkey(float f) {
    int b = as_int(f);
    return b >= 0 ? b : b ^ 0x7fffffff;
}

// Work-group minimum. Reduction i uses slot i % 3; once every work-item has passed its barrier,
// work-item 0 resets the slot of reduction i - 1 (read by everyone before this barrier) for
// reduction i + 2 (which starts after a later barrier).
inline float wg_min(volatile __local int *red, int *r, float v) {
    int s = *r % 3;
    atomic_min(&red[s], fkey(v));
    barrier(CLK_LOCAL_MEM_FENCE);
    float m = as_float(fkey(as_float(red[s])));
    if (get_local_id(0) == 0) red[(s + 2) % 3] = GW_NONE;
    *r += 1;
    return m;
}

inline int ctz64(ulong x) {
    return 63 - (int)clz(x & (~x + 1));
}

// One pass over the working set: the per-point unit vectors (X - P) / |X - P| of the points
// selected (mode 0, evaluation: clearance e < nreach; mode 1, away: inside the sphere of radius
// rho + off), summed in the CPU kernel's lane order. Mode 0 also gives the smallest clearance
// in the band (a work-group minimum) and this work-item's bits of the points below rclip.
// Returns (sum x, y, z, smallest clearance).
inline float4 wg_sum_pass(__local const float4 *ws, __local float *T, __local float *S, int tb, int n,
                          float3 X, float nreach, float rclip, float off, int away, ulong *nearbits,
                          volatile __local int *red, int *r, int *sp) {
    const int lid = get_local_id(0), W = get_local_size(0);
    const int c = lid >> 3, ln = lid & 7;
    float me = INFINITY, acc = 0.0f;
    ulong nb = 0;
    for (int base = 0; base < n; base += tb) {
        int m = min(tb, n - base);
        for (int j = lid; j < m; j += W) {
            int k = base + j;
            float4 q = ws[k];
            float dx = X.x - q.x, dy = X.y - q.y, dz = X.z - q.z;
            float d2 = dx * dx + dy * dy + dz * dz;
            float d = sqrt(d2);
            float inv = 0.0f;
            if (away) {
                float rc = q.w + off;
                float cc = d2 - rc * rc;
                if (cc < 0.0f && d > 0.0f) inv = 1.0f / d;
            } else {
                float e = d - q.w;
                if (e < nreach) {
                    me = fmin(me, e);
                    if (d > 0.0f) inv = 1.0f / d;
                }
                if (e < rclip) nb |= (ulong)1 << (k / W);
            }
            T[j] = dx * inv;
            T[tb + j] = dy * inv;
            T[2 * tb + j] = dz * inv;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid < 24)
            for (int j = ln; j < m; j += 8) acc += T[c * tb + j];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    // lane sums in S[parity]: the previous pass's readers are past a barrier of this one, or
    // (no points) read the other half
    __local float *Sp = S + 24 * *sp;
    *sp ^= 1;
    if (lid < 24) Sp[lid] = acc;
    float min_e = wg_min(red, r, me);   // (its barrier publishes the lane sums too)
    float sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int k = 0; k < 8; ++k) {
        sx += Sp[k];
        sy += Sp[8 + k];
        sz += Sp[16 + k];
    }
    *nearbits = nb;
    return (float4)(sx, sy, sz, min_e);
}

// The step limit along u (proxy.cl's clip_ws, per point), over this work-item's points below
// rclip; a work-group minimum.
inline float wg_clip(__local const float4 *ws, ulong nb, float3 X, float3 u, float off, volatile __local int *red,
                     int *r) {
    const int lid = get_local_id(0), W = get_local_size(0);
    float tm = INFINITY;
    while (nb) {
        int i = ctz64(nb);
        nb &= nb - 1;
        float4 q = ws[lid + i * W];
        float dx = X.x - q.x, dy = X.y - q.y, dz = X.z - q.z;
        float d2 = dx * dx + dy * dy + dz * dz;
        float b = u.x * dx + u.y * dy + u.z * dz;
        float rc = q.w + off;
        float c = d2 - rc * rc;
        float disc = b * b - c;
        float t = INFINITY;
        if (b < 0.0f) {
            if (c < 0.0f) t = 0.0f;
            else if (disc > 0.0f) t = c / (-b + sqrt(disc));
        }
        tm = fmin(tm, t);
    }
    return wg_min(red, r, tm);
}

inline int in_set(__global const float4 *pts, __global const float4 *vel, float dt, __global const int *order, int i,
                  int fixture, float3 X0, float r2, float4 *q) {
    int entry = order[i];
    if (fixture && entry >= 0) return 0;
    float4 p = point_at(pts, vel, i, entry, dt);
    float dx = p.x - X0.x, dy = p.y - X0.y, dz = p.z - X0.z;
    *q = p;
    return dx * dx + dy * dy + dz * dz <= r2;
}

// proxy.cl's gather into local memory: the points within radius of X0 in cell order; returns
// how many (more than cap: nothing written, the caller takes the hash path).
inline int wg_gather(__global const float4 *pts, __global const float4 *vel, float dt, __global const int *order,
                     __global const int *start, float4 grid, int4 dims, int span, float3 X0, float radius,
                     int fixture, float r1, __local float4 *ws, int cap, __local int *rowa, __local int *rowp,
                     __local int *scan) {
    const int lid = get_local_id(0), W = get_local_size(0);
    int4 hi;
    int4 lo = cell_range(X0, grid, dims, span, &hi);
    int ny = hi.y - lo.y + 1, nz = hi.z - lo.z + 1;
    int nrows = (lo.x <= hi.x && ny > 0 && nz > 0) ? ny * nz : 0;
    float r2 = radius * radius;
    float4 q;
    int serial = nrows > GW_ROWS;   // a wide reach on a fine grid: one work-item gathers
    if (serial) nrows = 0;
    for (int rr = lid; rr < nrows; rr += W) {
        int base = ((lo.z + rr / ny) * dims.y + lo.y + rr % ny) * dims.x;
        int a = start[base + lo.x];
        rowa[rr] = a;
        rowp[rr + 1] = start[base + hi.x + 1] - a;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) {
        rowp[0] = 0;
        for (int rr = 0; rr < nrows; ++rr) rowp[rr + 1] += rowp[rr];
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int total = rowp[nrows];
    int C = (total + W - 1) / W;
    int k0 = min(lid * C, total), k1 = min(k0 + C, total);
    int r0 = 0;
    while (r0 < nrows && rowp[r0 + 1] <= k0) ++r0;
    // (row by row: the inner loop's loads do not depend on one another, so the compiler can
    // have several in flight)
    int cnt = 0;
    for (int rr = r0; rr < nrows && rowp[rr] < k1; ++rr) {
        int ia = rowa[rr] - rowp[rr];
        int kb = min(k1, rowp[rr + 1]);
        for (int k = max(k0, rowp[rr]); k < kb; ++k) cnt += in_set(pts, vel, dt, order, ia + k, fixture, X0, r2, &q);
    }
    // inclusive scan of the counts over the work-items (Hillis-Steele, double-buffered)
    scan[lid] = cnt;
    barrier(CLK_LOCAL_MEM_FENCE);
    int pin = 0;
    for (int o = 1; o < W; o <<= 1) {
        int v = scan[pin * W + lid];
        if (lid >= o) v += scan[pin * W + lid - o];
        scan[(1 - pin) * W + lid] = v;
        pin = 1 - pin;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    int n = scan[pin * W + W - 1];
    int at = scan[pin * W + lid] - cnt;
    if (serial && lid == 0) {
        n = 0;
        for (int iz = lo.z; iz <= hi.z; ++iz)
            for (int iy = lo.y; iy <= hi.y; ++iy) {
                int base = (iz * dims.y + iy) * dims.x;
                int a = start[base + lo.x], e = start[base + hi.x + 1];
                for (int i = a; i < e; ++i)
                    if (in_set(pts, vel, dt, order, i, fixture, X0, r2, &q)) {
                        if (n < cap) ws[n] = (float4)(q.x, q.y, q.z, fixture ? q.w : r1);
                        ++n;
                    }
            }
        rowp[0] = n;
    }
    if (!serial && n <= cap) {
        for (int rr = r0; rr < nrows && rowp[rr] < k1; ++rr) {
            int ia = rowa[rr] - rowp[rr];
            int kb = min(k1, rowp[rr + 1]);
            for (int k = max(k0, rowp[rr]); k < kb; ++k)
                if (in_set(pts, vel, dt, order, ia + k, fixture, X0, r2, &q))
                    ws[at++] = (float4)(q.x, q.y, q.z, fixture ? q.w : r1);
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    return serial ? rowp[0] : n;
}

// Arguments 0-18 as proxy_tick's (wsbuf and nearbuf unused; cap: points of the local working
// set), then the local working set (cap float4), the term buffer (3 tb floats), tb (a multiple
// of the work-group size and of 8) and ocap (proxy_tick's argument 19). One work-group of
// W <= GW_MAXW work-items a proxy.
__kernel void proxy_tick_wg(__global const float4 *pts, __global const int *order, __global const int *start,
                            float4 grid, int4 dims, int n_proxies, __global float4 *pos, __global const float *hips,
                            __global float *out, __global float *wsbuf, int cap, __constant float *prm,
                            int fixture, int max_steps, int gspan, int rspan, __global const float4 *vel, float dt,
                            __global int *nearbuf, __local float4 *ws, __local float *T, int tb, int ocap) {
    __local int rowa[GW_ROWS], rowp[GW_ROWS + 1], scan[2 * GW_MAXW], red[3];
    __local float S[48];
    const int p = get_group_id(0), lid = get_local_id(0);
    if (p >= n_proxies) return;
    if (lid < 3) red[lid] = GW_NONE;
    barrier(CLK_LOCAL_MEM_FENCE);
    int rn = 0, sp = 0;
    float3 X = pos[p].xyz, H = vload3(p, hips), X0 = X;
    const float r1 = P_R1, band = P_BAND, nreach = P_NREACH, skin2 = P_SKIN * P_SKIN;
    const float rclip = 0.5f * band + P_MARGIN + P_STEP * 1.0001f + 1.0e-6f;   // as proxy_tick
    int n = wg_gather(pts, vel, dt, order, start, grid, dims, gspan, X0, P_GATHER, fixture, r1, ws, cap, rowa, rowp,
                      scan);
    // Every barrier below sits in a loop whose trip count is the same in every work-item (no
    // barrier under an if, no break out of a loop holding one): PoCL compiles barriers under
    // conditions by duplicating the code after them, which made this kernel take minutes.
    int steps = 0, conv = 0, st = FREE, done = 0;
    float3 nrm = (float3)(0.0f);
    float min_e = INFINITY;
    float3 uprev = (float3)(0.0f);  // direction of the last sliding or free step
    ulong nb = 0;
    for (int it = 0; !done; ++it) {
        float3 dx0 = X - X0;
        int regather = dx0.x * dx0.x + dx0.y * dx0.y + dx0.z * dx0.z > skin2;
        for (int g = 0; g < regather; ++g) {   // wandered off its working set
            X0 = X;
            n = wg_gather(pts, vel, dt, order, start, grid, dims, gspan, X0, P_GATHER, fixture, r1, ws, cap, rowa,
                          rowp, scan);
        }
        int direct = n > cap;
        int nw = direct ? 0 : n;   // (the hash path runs the local passes over no points)
        float4 s4 = wg_sum_pass(ws, T, S, tb, nw, X, nreach, rclip, 0.0f, 0, &nb, red, &rn, &sp);
        float3 nsum = s4.xyz;
        min_e = s4.w;
        if (direct) {
            Eval ev = eval_hash(pts, vel, dt, order, start, grid, dims, rspan, X, fixture, r1, nreach);
            nsum = ev.nsum;
            min_e = ev.min_e;
        }
        st = state_of(min_e, band);
        nrm = normal_of(nsum);
        done = it == max_steps;   // budget spent: state and normal at the final position
        float3 v = H - X;
        float vl = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
        float vn = v.x * nrm.x + v.y * nrm.y + v.z * nrm.z;
        float3 vp = v - vn * nrm;
        float vpl = sqrt(vp.x * vp.x + vp.y * vp.y + vp.z * vp.z);
        int has_n = nrm.x != 0.0f || nrm.y != 0.0f || nrm.z != 0.0f;
        // contact rules (rule 3/4): along v with the HIP outside or no normal, else along vp
        float3 u2 = (float3)(0.0f);
        float L2 = 0.0f;
        if (st == FREE || vn > 0.0f || !has_n) {
            if (vl > 0.0f) { u2 = v / vl; L2 = vl; }
        } else if (vpl > 0.0f) {
            u2 = vp / vpl; L2 = vpl;
        }
        L2 = fmin(L2, P_STEP);
        int push = st == ENTRENCHED && has_n;  // push-out along n first
        float Lp = fmin(0.5f * band - min_e, P_STEP);
        int buried = st == ENTRENCHED && min_e < -P_SLACK - P_MARGIN;
        float lim = st == FREE ? 0.5f * band : (buried ? min_e : -P_SLACK);
        float off = lim + P_MARGIN;
        // clipping, up to three tries (proxy_tick's order): the push-out along n, then (blocked)
        // the contact rule's direction, then (buried and blocked again) away from the deepest points
        float3 u = push ? nrm : u2;
        float Lc = push ? Lp : L2;
        int along_n = push;
        float s = 0.0f;
        int stop = done;
        for (int attempt = 0; !stop; ++attempt) {
            for (int a = 0; a < (attempt == 2); ++a) {
                ulong none;
                float3 as = wg_sum_pass(ws, T, S, tb, nw, X, nreach, rclip, off, 1, &none, red, &rn, &sp).xyz;
                if (direct) as = away_hash(pts, vel, dt, order, start, grid, dims, rspan, X, off, fixture, r1);
                u = normal_of(as);
                Lc = Lp;
                along_n = 1;
            }
            float t = wg_clip(ws, direct ? (ulong)0 : nb, X, u, off, red, &rn);
            if (direct) t = clip_hash(pts, vel, dt, order, start, grid, dims, rspan, X, u, off, fixture, r1);
            s = fmax(fmin(Lc, t), 0.0f);
            if (attempt == 2 && !(u.x != 0.0f || u.y != 0.0f || u.z != 0.0f)) s = 0.0f;
            stop = s >= P_TOL || attempt == 2 || (attempt == 0 && !push) || (attempt == 1 && !buried);
            if (attempt == 0 && !stop) {   // push-out blocked: the contact rule's direction instead
                along_n = 0;
                u = u2;
                Lc = L2;
            }
        }
        if (!done) {
            if (s < P_TOL) {
                conv = 1;
                done = 1;
            } else if (!along_n && u.x * uprev.x + u.y * uprev.y + u.z * uprev.z < P_TURN_BACK) {
                conv = 1;   // a slide turning back against the previous one: rocking in a crease
                done = 1;
            } else {
                if (!along_n) uprev = u;
                X = X + s * u;
                ++steps;
            }
        }
    }
    if (lid == 0) {
        pos[p] = (float4)(X, 0.0f);
        write_out(out, ocap, p, X, min_e, nrm, st, steps, conv);
    }
}
