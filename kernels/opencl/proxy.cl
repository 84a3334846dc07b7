// Batched proxy movement of one haptic tick (SPEC 2, 3). Mirrors kernels/reference/proxy.py;
// the algorithm is described in kernels/proxy.py.
//
// One work-item per proxy runs every step of the tick. Per tick (and whenever the proxy wanders
// further than `skin` from where it gathered) it copies the points within reach + skin of its
// position from the spatial hash into its working set: structure-of-arrays rows of `cap` floats
// (x, y, z, rho) padded to a multiple of VW with far-away points, which the steps scan VW points
// at a time with explicit vector types. If more than `cap` points are in reach the proxy scans
// the hash cells directly instead (slower, same result).
// Snapshot layout (frames.cl): pts in pixel order, order[] = pixel | protected << 31 sorted by cell,
// vel[] = each point's velocity in the order of order[] (kernels/motion.py). With dt > 0 every
// point is taken at p + v dt and the spans gspan / rspan include the motion's extra reach.
#pragma OPENCL FP_CONTRACT OFF

#define VW 8   // LANES in kernels/proxy.py: the reference sums the normal in the same 8 lanes
typedef float8 vf;
typedef int8 vi;
#define FAR 1.0e18f

// The working-set loops use no OpenCL builtin: PoCL 3.0 (the pip wheel's, LLVM 14) calls its
// vector builtins out of line, and each call spills every live vector register to the stack
// (a step cost 2-3x more). Loads are vector dereferences (working sets are 32-byte aligned),
// selects and minima are vector conditionals, and on x86 the square root is the compiler's
// packed sqrt intrinsic: IEEE correctly rounded, as sqrt() is under
// -cl-fp32-correctly-rounded-divide-sqrt, so every result is unchanged.
#define VLD(p) (*(__global const vf *)(p))
#define VSEL(m, a, b) ((m) ? (a) : (b))
#define VMIN(a, b) ((a) < (b) ? (a) : (b))
#define VMAX0(a) ((a) > (vf)(0.0f) ? (a) : (vf)(0.0f))
#if defined(__AVX__)
#define VSQRT(x) __builtin_ia32_sqrtps256(x)
#elif defined(__SSE__)
#define VSQRT(x) ((vf)(__builtin_ia32_sqrtps((x).lo), __builtin_ia32_sqrtps((x).hi)))
#else
#define VSQRT(x) sqrt(x)
#endif
// any lane of a comparison mask set
#define VANY(m) vany(m)
inline int vany(vi m) {
    int4 b = m.lo | m.hi;
    int2 c = b.lo | b.hi;
    return (c.x | c.y) != 0;
}

// Scalar parameters, packed by kernels/opencl/proxy.py (keep in sync):
// 0 r1, 1 band = r2 - r1, 2 nreach = r3 - r1, 3 step, 4 tol, 5 slack, 6 skin, 7 gather radius,
// 8 reach (hash scan radius of the direct path), 9 margin, 10 turn_back_cos
#define P_R1 prm[0]
#define P_BAND prm[1]
#define P_NREACH prm[2]
#define P_STEP prm[3]
#define P_TOL prm[4]
#define P_SLACK prm[5]
#define P_SKIN prm[6]
#define P_GATHER prm[7]
#define P_MARGIN prm[9]
#define P_TURN_BACK prm[10]

#define FREE 0
#define CONTACT 1
#define ENTRENCHED 2

typedef struct {
    float3 nsum;
    float min_e;
    int nnear;   // chunks of the working set listed as within the clip's reach
} Eval;

// Point `entry` (at position i of the cell-sorted order) where the tick predicts it: p + v dt
// (kernels/motion.py); dt = 0 leaves it untouched.
inline float4 point_at(__global const float4 *pts, __global const float4 *vel, int i, int entry, float dt) {
    float4 p = pts[entry & 0x7fffffff];
    if (dt > 0.0f) {
        float4 v = vel[i];
        p.x = p.x + v.x * dt;
        p.y = p.y + v.y * dt;
        p.z = p.z + v.z * dt;
    }
    return p;
}

inline int4 cell_range(float3 q, float4 grid, int4 dims, int span, int4 *hi) {
    int cx = (int)clamp(floor((q.x - grid.x) * grid.w), (float)(-span - 1), (float)(dims.x + span));
    int cy = (int)clamp(floor((q.y - grid.y) * grid.w), (float)(-span - 1), (float)(dims.y + span));
    int cz = (int)clamp(floor((q.z - grid.z) * grid.w), (float)(-span - 1), (float)(dims.z + span));
    *hi = (int4)(min(cx + span, dims.x - 1), min(cy + span, dims.y - 1), min(cz + span, dims.z - 1), 0);
    return (int4)(max(cx - span, 0), max(cy - span, 0), max(cz - span, 0), 0);
}

// Copy the points within `radius` of X0 into the working set; return how many there are
// (possibly more than cap: then nothing beyond cap is written and the caller scans the hash).
inline int gather(__global const float4 *pts, __global const float4 *vel, float dt,
                  __global const int *order, __global const int *start, float4 grid, int4 dims, int span, float3 X0, float radius, int fixture, float r1,
                  __global float *ws, int cap) {
    int4 hi;
    int4 lo = cell_range(X0, grid, dims, span, &hi);
    float r2 = radius * radius;
    int n = 0;
    __global float *wx = ws, *wy = ws + cap, *wz = ws + 2 * cap, *wr = ws + 3 * cap;
    for (int iz = lo.z; iz <= hi.z; ++iz)
        for (int iy = lo.y; iy <= hi.y; ++iy) {
            if (lo.x > hi.x) continue;
            int base = (iz * dims.y + iy) * dims.x;
            int a = start[base + lo.x], e = start[base + hi.x + 1];
            for (int i = a; i < e; ++i) {
                int entry = order[i];
                if (fixture && entry >= 0) continue;
                float4 p = point_at(pts, vel, i, entry, dt);
                float dx = p.x - X0.x, dy = p.y - X0.y, dz = p.z - X0.z;
                float d2 = dx * dx + dy * dy + dz * dz;
                if (d2 <= r2) {
                    if (n < cap) {
                        wx[n] = p.x; wy[n] = p.y; wz[n] = p.z; wr[n] = fixture ? p.w : r1;
                    }
                    ++n;
                }
            }
        }
    if (n <= cap) {
        int padded = min(cap, (n + VW - 1) / VW * VW);
        for (int i = n; i < padded; ++i) { wx[i] = FAR; wy[i] = FAR; wz[i] = FAR; wr[i] = 0.0f; }
    }
    return n;
}

// ---- evaluation: clearances, normal sum, smallest clearance within the normal band ---------
// It also lists in nl the chunks (their first index) holding a point with clearance below
// rclip: no step from X can reach the others (see proxy_tick), so the clip scans only these.
inline Eval eval_ws(__global const float *ws, int cap, int n, float3 X, float nreach, float rclip,
                    __global int *nl) {
    __global const float *wx = ws, *wy = ws + cap, *wz = ws + 2 * cap, *wr = ws + 3 * cap;
    vf ax = 0.0f, ay = 0.0f, az = 0.0f, me = INFINITY;
    int nn = 0;
    for (int i = 0; i < n; i += VW) {
        vf dx = (vf)(X.x) - VLD(wx + i);
        vf dy = (vf)(X.y) - VLD(wy + i);
        vf dz = (vf)(X.z) - VLD(wz + i);
        vf d2 = dx * dx + dy * dy + dz * dz;
        vf d = VSQRT(d2);
        vf e = d - VLD(wr + i);
        nl[nn] = i;
        nn += VANY(e < (vf)(rclip));
        vi inb = e < (vf)(nreach);
        me = VMIN(VSEL(inb, e, (vf)(INFINITY)), me);
        vf inv = VSEL(inb & (d > (vf)(0.0f)), (vf)(1.0f) / d, (vf)(0.0f));
        ax += dx * inv; ay += dy * inv; az += dz * inv;
    }
    Eval r;
    float m = INFINITY, sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int k = 0; k < VW; ++k) {
        m = fmin(m, me[k]);
        sx += ax[k]; sy += ay[k]; sz += az[k];
    }
    r.nsum = (float3)(sx, sy, sz);
    r.min_e = m;
    r.nnear = nn;
    return r;
}

inline Eval eval_hash(__global const float4 *pts, __global const float4 *vel, float dt,
                      __global const int *order, __global const int *start,
                      float4 grid, int4 dims, int span, float3 X, int fixture, float r1, float nreach) {
    int4 hi;
    int4 lo = cell_range(X, grid, dims, span, &hi);
    float m = INFINITY, sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int iz = lo.z; iz <= hi.z; ++iz)
        for (int iy = lo.y; iy <= hi.y; ++iy) {
            if (lo.x > hi.x) continue;
            int base = (iz * dims.y + iy) * dims.x;
            int a = start[base + lo.x], e_ = start[base + hi.x + 1];
            for (int i = a; i < e_; ++i) {
                int entry = order[i];
                if (fixture && entry >= 0) continue;
                float4 p = point_at(pts, vel, i, entry, dt);
                float dx = X.x - p.x, dy = X.y - p.y, dz = X.z - p.z;
                float d2 = dx * dx + dy * dy + dz * dz;
                float d = sqrt(d2);
                float e = d - (fixture ? p.w : r1);
                if (e < nreach) {
                    m = fmin(m, e);
                    if (d > 0.0f) {
                        float inv = 1.0f / d;
                        sx += dx * inv; sy += dy * inv; sz += dz * inv;
                    }
                }
            }
        }
    Eval r;
    r.nsum = (float3)(sx, sy, sz);
    r.min_e = m;
    r.nnear = 0;
    return r;
}

// ---- clipping of a step along u (kernels/proxy.py, step 3) ---------------------------------
// off = limit F + margin. A clear point (c = d2 - (rho + off)^2 >= 0) stops the step where its
// clearance reaches F + margin (swept sphere); a point at the limit (c < 0) may not be
// approached at all (b < 0 gives 0). Scans the nn chunks listed in nl by eval_ws.
inline float clip_ws(__global const float *ws, int cap, __global const int *nl, int nn, float3 X, float3 u, float off) {
    __global const float *wx = ws, *wy = ws + cap, *wz = ws + 2 * cap, *wr = ws + 3 * cap;
    vf tmin = INFINITY;
    for (int k = 0; k < nn; ++k) {
        int i = nl[k];
        vf dx = (vf)(X.x) - VLD(wx + i);
        vf dy = (vf)(X.y) - VLD(wy + i);
        vf dz = (vf)(X.z) - VLD(wz + i);
        vf d2 = dx * dx + dy * dy + dz * dz;
        vf b = (vf)(u.x) * dx + (vf)(u.y) * dy + (vf)(u.z) * dz;
        vf rc = VLD(wr + i) + (vf)(off);
        vf c = d2 - rc * rc;
        vf disc = b * b - c;
        vi neg = b < (vf)(0.0f);
        vi outside = (c >= (vf)(0.0f)) & neg & (disc > (vf)(0.0f));
        vi atlim = (c < (vf)(0.0f)) & neg;
        vf t = VSEL(atlim, (vf)(0.0f), (vf)(INFINITY));
        if (VANY(outside)) {  // most chunks hold no point the step could reach: skip sqrt and divide
            vf dm = VMAX0(disc);
            vf t_out = c / (-b + VSQRT(dm));
            t = VSEL(outside, t_out, t);
        }
        tmin = VMIN(t, tmin);
    }
    float m = INFINITY;
    for (int k = 0; k < VW; ++k) m = fmin(m, tmin[k]);
    return m;
}

inline float clip_hash(__global const float4 *pts, __global const float4 *vel, float dt,
                      __global const int *order, __global const int *start,
                       float4 grid, int4 dims, int span, float3 X, float3 u, float off, int fixture, float r1) {
    int4 hi;
    int4 lo = cell_range(X, grid, dims, span, &hi);
    float m = INFINITY;
    for (int iz = lo.z; iz <= hi.z; ++iz)
        for (int iy = lo.y; iy <= hi.y; ++iy) {
            if (lo.x > hi.x) continue;
            int base = (iz * dims.y + iy) * dims.x;
            int a = start[base + lo.x], e_ = start[base + hi.x + 1];
            for (int i = a; i < e_; ++i) {
                int entry = order[i];
                if (fixture && entry >= 0) continue;
                float4 p = point_at(pts, vel, i, entry, dt);
                float dx = X.x - p.x, dy = X.y - p.y, dz = X.z - p.z;
                float d2 = dx * dx + dy * dy + dz * dz;
                float b = u.x * dx + u.y * dy + u.z * dz;
                float rc = (fixture ? p.w : r1) + off;
                float c = d2 - rc * rc;
                float disc = b * b - c;
                float t = INFINITY;
                if (c >= 0.0f && b < 0.0f && disc > 0.0f) t = c / (-b + sqrt(disc));
                else if (c < 0.0f && b < 0.0f) t = 0.0f;
                m = fmin(m, t);
            }
        }
    return m;
}

// ---- direction away from the points at the limit (c < 0), summed like the normal ----------
inline float3 away_ws(__global const float *ws, int cap, int n, float3 X, float off) {
    __global const float *wx = ws, *wy = ws + cap, *wz = ws + 2 * cap, *wr = ws + 3 * cap;
    vf ax = 0.0f, ay = 0.0f, az = 0.0f;
    for (int i = 0; i < n; i += VW) {
        vf dx = (vf)(X.x) - VLD(wx + i);
        vf dy = (vf)(X.y) - VLD(wy + i);
        vf dz = (vf)(X.z) - VLD(wz + i);
        vf d2 = dx * dx + dy * dy + dz * dz;
        vf d = VSQRT(d2);
        vf rc = VLD(wr + i) + (vf)(off);
        vf c = d2 - rc * rc;
        vf inv = VSEL((c < (vf)(0.0f)) & (d > (vf)(0.0f)), (vf)(1.0f) / d, (vf)(0.0f));
        ax += dx * inv; ay += dy * inv; az += dz * inv;
    }
    float sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int k = 0; k < VW; ++k) { sx += ax[k]; sy += ay[k]; sz += az[k]; }
    return (float3)(sx, sy, sz);
}

inline float3 away_hash(__global const float4 *pts, __global const float4 *vel, float dt,
                      __global const int *order, __global const int *start,
                        float4 grid, int4 dims, int span, float3 X, float off, int fixture, float r1) {
    int4 hi;
    int4 lo = cell_range(X, grid, dims, span, &hi);
    float sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int iz = lo.z; iz <= hi.z; ++iz)
        for (int iy = lo.y; iy <= hi.y; ++iy) {
            if (lo.x > hi.x) continue;
            int base = (iz * dims.y + iy) * dims.x;
            int a = start[base + lo.x], e_ = start[base + hi.x + 1];
            for (int i = a; i < e_; ++i) {
                int entry = order[i];
                if (fixture && entry >= 0) continue;
                float4 p = point_at(pts, vel, i, entry, dt);
                float dx = X.x - p.x, dy = X.y - p.y, dz = X.z - p.z;
                float d2 = dx * dx + dy * dy + dz * dz;
                float d = sqrt(d2);
                float rc = (fixture ? p.w : r1) + off;
                float c = d2 - rc * rc;
                if (c < 0.0f && d > 0.0f) {
                    float inv = 1.0f / d;
                    sx += dx * inv; sy += dy * inv; sz += dz * inv;
                }
            }
        }
    return (float3)(sx, sy, sz);
}

inline int state_of(float min_e, float band) {
    return min_e < 0.0f ? ENTRENCHED : (min_e < band ? CONTACT : FREE);
}

inline float3 normal_of(float3 ns) {
    float nn = sqrt(ns.x * ns.x + ns.y * ns.y + ns.z * ns.z);
    return nn > 0.0f ? ns / nn : (float3)(0.0f);
}

// The tick's results of proxy p, written in the layout of the batch's host arrays for a batch of
// ocap proxies (kernels/opencl/proxy.py, ``out_block``), so that the host reads them straight into
// those arrays (on PoCL's in-thread device the kernel writes them there itself): the positions
// (3 ocap floats, world m), the nearest clearances (ocap floats, m), the normals (3 ocap floats),
// the states and the steps (ocap ints each), the converged flags (ocap bytes).
inline void write_out(__global float *out, int ocap, int p, float3 X, float min_e, float3 nrm, int st, int steps,
                      int conv) {
    vstore3(X, p, out);
    out[3 * ocap + p] = min_e;
    vstore3(nrm, p, out + 4 * ocap);
    ((__global int *)(out + 7 * ocap))[p] = st;
    ((__global int *)(out + 8 * ocap))[p] = steps;
    ((__global uchar *)(out + 9 * ocap))[p] = (uchar)conv;
}

// hips: 3 floats a proxy (world m); out: see write_out (ocap: the batch's capacity)
__kernel void proxy_tick(__global const float4 *pts, __global const int *order, __global const int *start,
                         float4 grid, int4 dims, int n_proxies, __global float4 *pos, __global const float *hips,
                         __global float *out, __global float *wsbuf, int cap, __constant float *prm,
                         int fixture, int max_steps, int gspan, int rspan, __global const float4 *vel, float dt,
                         __global int *nearbuf, int ocap) {
    int p = get_global_id(0);
    if (p >= n_proxies) return;
    __global float *ws = wsbuf + (size_t)p * 4 * cap;
    __global int *nl = nearbuf + (size_t)p * (cap / VW);
    float3 X = pos[p].xyz, H = vload3(p, hips), X0 = X;
    const float r1 = P_R1, band = P_BAND, nreach = P_NREACH, skin2 = P_SKIN * P_SKIN;
    // A step's limit F is at most band / 2 (slack >= 0) and its length at most step, so a point
    // with clearance e >= band / 2 + margin + step cannot stop it: its hit time t >= e - F -
    // margin >= step >= L. The 1 um (and 1e-4 step) over that keeps float32 rounding of e and t
    // out of the decision: the clipped length is exactly the one a scan of every point gives.
    const float rclip = 0.5f * band + P_MARGIN + P_STEP * 1.0001f + 1.0e-6f;
    int n = gather(pts, vel, dt, order, start, grid, dims, gspan, X0, P_GATHER, fixture, r1, ws, cap);
    int steps = 0, conv = 0, st = FREE;
    float3 nrm = (float3)(0.0f);
    float min_e = INFINITY;
    float3 uprev = (float3)(0.0f);  // direction of the last sliding or free step
    for (int it = 0; it <= max_steps; ++it) {
        float3 dx0 = X - X0;
        if (dx0.x * dx0.x + dx0.y * dx0.y + dx0.z * dx0.z > skin2) {
            X0 = X;
            n = gather(pts, vel, dt, order, start, grid, dims, gspan, X0, P_GATHER, fixture, r1, ws, cap);
        }
        int direct = n > cap;
        Eval ev = direct ? eval_hash(pts, vel, dt, order, start, grid, dims, rspan, X, fixture, r1, nreach)
                         : eval_ws(ws, cap, n, X, nreach, rclip, nl);
        min_e = ev.min_e;
        st = state_of(min_e, band);
        nrm = normal_of(ev.nsum);
        if (it == max_steps) break;  // budget spent: state and normal at the final position
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
        float3 u = push ? nrm : u2;
        float Lp = fmin(0.5f * band - min_e, P_STEP);
        float L = push ? Lp : L2;
        // limit F: mid-band for a free step, -slack otherwise, min e where buried (the deepest
        // penetration never grows); off = F + margin
        int buried = st == ENTRENCHED && min_e < -P_SLACK - P_MARGIN;
        float lim = st == FREE ? 0.5f * band : (buried ? min_e : -P_SLACK);
        float off = lim + P_MARGIN;
        float t = direct ? clip_hash(pts, vel, dt, order, start, grid, dims, rspan, X, u, off, fixture, r1)
                         : clip_ws(ws, cap, nl, ev.nnear, X, u, off);
        float s = fmax(fmin(L, t), 0.0f);
        int along_n = push;
        if (push && s < P_TOL) {  // push-out blocked: the contact rule's direction instead
            along_n = 0;
            u = u2;
            t = direct ? clip_hash(pts, vel, dt, order, start, grid, dims, rspan, X, u, off, fixture, r1)
                       : clip_ws(ws, cap, nl, ev.nnear, X, u, off);
            s = fmax(fmin(L2, t), 0.0f);
            if (buried && s < P_TOL) {  // both blocked: away from the deepest points
                along_n = 1;
                u = normal_of(direct ? away_hash(pts, vel, dt, order, start, grid, dims, rspan, X, off, fixture, r1)
                                     : away_ws(ws, cap, n, X, off));
                t = direct ? clip_hash(pts, vel, dt, order, start, grid, dims, rspan, X, u, off, fixture, r1)
                           : clip_ws(ws, cap, nl, ev.nnear, X, u, off);
                s = u.x != 0.0f || u.y != 0.0f || u.z != 0.0f ? fmax(fmin(Lp, t), 0.0f) : 0.0f;
            }
        }
        if (s < P_TOL) { conv = 1; break; }
        if (!along_n) {  // a slide turning back against the previous one: rocking in a crease
            if (u.x * uprev.x + u.y * uprev.y + u.z * uprev.z < P_TURN_BACK) { conv = 1; break; }
            uprev = u;
        }
        X = X + s * u;
        ++steps;
    }
    pos[p] = (float4)(X, 0.0f);
    write_out(out, ocap, p, X, min_e, nrm, st, steps, conv);
}
