// Frame pipeline and spatial hash build (SPEC 1). Mirrors kernels/reference/pipeline.py.
// Launched once per camera with that camera's parameters as uniform arguments:
//   pose = R (row-major, 9), t (3), near bias a, b, unused (2)   camera -> world; a reading z is
//          taken at z - max(a, b z^2), the near end of its depth step (Camera.near_bias; 0, 0: as read)
//   cam  = depth_scale, z_min, z_max, noise a, noise b, lateral (m per m of depth), has_color, has_mask
//   cami = pixel offset in the rig, pixel count, max_code, camera index
// The hash is a counting sort of pixel indices: classify (attributes and cell per pixel, written
// in pixel order), then the cell sort (kernels/opencl/cell_sort.py): here its CPU shape, count_runs,
// scan, scatter (4-byte entries only), sort_cells; its GPU shape is cell_sort_gpu.cl. A snapshot is
//   pts[pix] = (x, y, z, r_f) and sigma[pix] for every surviving pixel (pixel order), and
//   order[start[c] .. start[c+1]) = entries of cell c, entry = pix | protected << 31, in
//   ascending pixel order within the cell (the reference's stable sort: camera, then pixel).
// The scatter's order within a cell depends on which work-item's atomic came first; sort_cells
// puts it in pixel order, so the same frames give the same snapshot on every run and device.
// Moving only 4-byte entries keeps the scattered writes in cache (moving 26-byte points was 15x slower on PoCL).
#pragma OPENCL FP_CONTRACT OFF

// floor() for |v| < 2^31 without a libm call (PoCL does not vectorise floor).
inline int ifloor(float v) { int i = (int)v; return i - (v < (float)i); }
inline int iclamp(int v, int hi) { return v < 0 ? 0 : (v > hi ? hi : v); }

// World point of pixel `pix`; returns 1 when the reading is valid and inside the workspace.
// `near` (a constant of each kernel below): the reading at the near end of its depth step.
inline int world_point(int pix, __global const ushort *depth, __global const float2 *rays,
                       float16 pose, float8 cam, int max_code, float4 wmin, float4 wmax,
                       float *x, float *y, float *w, float *zc, const int near) {
    uint d = depth[pix];
    float z = (float)d * cam.s0;
    if (near) {
        float bq = pose.sd * z * z;
        z = z - (bq > pose.sc ? bq : pose.sc);
    }
    float2 r = rays[pix];
    float xc = r.x * z, yc = r.y * z;
    *x = pose.s0 * xc + pose.s1 * yc + pose.s2 * z + pose.s9;
    *y = pose.s3 * xc + pose.s4 * yc + pose.s5 * z + pose.sa;
    *w = pose.s6 * xc + pose.s7 * yc + pose.s8 * z + pose.sb;
    *zc = z;
    return d != 0u && d != (uint)max_code && z >= cam.s1 && z <= cam.s2 &&
           *x >= wmin.x && *y >= wmin.y && *w >= wmin.z && *x < wmax.x && *y < wmax.y && *w < wmax.z;
}

// grid = (origin.xyz, 1 / cell size); points are inside the workspace, so the floor is in range.
inline int cell_index(float x, float y, float w, float4 grid, int4 dims) {
    int ix = iclamp(ifloor((x - grid.x) * grid.w), dims.x - 1);
    int iy = iclamp(ifloor((y - grid.y) * grid.w), dims.y - 1);
    int iz = iclamp(ifloor((w - grid.z) * grid.w), dims.z - 1);
    return (iz * dims.y + iy) * dims.x + ix;
}

__kernel void zero_ints(__global int *a, int n) {
    int i = get_global_id(0);
    if (i < n) a[i] = 0;
}

// sqrt(lambda_max) of C = sz^2 r r^T + sl^2 (I - e_z e_z^T), r = (rx, ry, 1): on span{(rx, ry, 0), e_z}
// C is [[sz^2 rho^2 + sl^2, sz^2 rho], [sz^2 rho, sz^2]] (rho^2 = rx^2 + ry^2); its larger eigenvalue is
// lambda_max (the third, sl^2, is smaller). The discriminant is written as a sum of squares.
inline float sigma_max(float sz, float sl, float rx, float ry) {
    float s2 = sz * sz, l2 = sl * sl, rho2 = rx * rx + ry * ry;
    float t = s2 * (1.0f + rho2);
    float dd = t - l2;
    return sqrt(0.5f * (t + l2 + sqrt(dd * dd + 4.0f * l2 * s2 * rho2)));
}

// Attributes and cell of every pixel of one camera (cell -1: invalid or outside the workspace).
// sel: 0 all, 1 box, 2 colour range, 3 mask.  radius = (r_base, k_sigma, r_max, adaptive).
// Two kernels: `classify` takes the readings as read, `classify_near` at the near end of their
// steps (Camera.near_reading). One kernel with the bias always applied (0 for readings as read)
// made PoCL's ingest about 10 % slower.
#define CLASSIFY_PARAMS __global const ushort *depth, __global const float2 *rays, \
    float16 pose, float8 cam, int4 cami, float4 wmin, float4 wmax, float4 grid, int4 dims, \
    int sel, float4 box_min, float4 box_max, int4 col_lo, int4 col_hi, \
    __global const uchar *color, __global const uchar *mask, float4 radius, \
    __global int *pix_cell, __global uchar *pix_prot, __global float4 *pts, __global float *sig
#define CLASSIFY_ARGS depth, rays, pose, cam, cami, wmin, wmax, grid, dims, sel, box_min, box_max, col_lo, col_hi, \
    color, mask, radius, pix_cell, pix_prot, pts, sig

inline void classify_pixel(CLASSIFY_PARAMS, const int near) {
    int i = get_global_id(0);
    if (i >= cami.y) return;
    int pix = cami.x + i;
    float x, y, w, z;
    if (!world_point(pix, depth, rays, pose, cam, cami.z, wmin, wmax, &x, &y, &w, &z, near)) {
        pix_cell[pix] = -1;
        return;
    }
    pix_cell[pix] = cell_index(x, y, w, grid, dims);
    float2 r = rays[pix];
    float sigma = sigma_max(cam.s3 + cam.s4 * z * z, cam.s5 * z, r.x, r.y);
    float rf = radius.w != 0.0f ? min(radius.x + radius.y * sigma, radius.z) : radius.x;
    int prot = 1;
    if (sel == 1) {
        prot = x >= box_min.x && y >= box_min.y && w >= box_min.z && x <= box_max.x && y <= box_max.y && w <= box_max.z;
    } else if (sel == 2) {
        if (cam.s6 == 0.0f) prot = 0;
        else {
            int cr = color[3 * pix], cg = color[3 * pix + 1], cb = color[3 * pix + 2];
            prot = cr >= col_lo.x && cg >= col_lo.y && cb >= col_lo.z && cr <= col_hi.x && cg <= col_hi.y && cb <= col_hi.z;
        }
    } else if (sel == 3) {
        prot = cam.s7 != 0.0f && mask[pix] != 0;
    }
    pix_prot[pix] = (uchar)prot;
    pts[pix] = (float4)(x, y, w, rf);
    sig[pix] = sigma;
}

__kernel void classify(CLASSIFY_PARAMS) { classify_pixel(CLASSIFY_ARGS, 0); }
__kernel void classify_near(CLASSIFY_PARAMS) { classify_pixel(CLASSIFY_ARGS, 1); }

// Count per cell and rank per pixel over the whole rig. Each work-item walks `per` consecutive
// pixels; neighbouring pixels of a depth image mostly share a cell, so one atomic_add per run of
// equal cells replaces one atomic per pixel (per = 1 is the plain form, for GPUs).
__kernel void count_runs(__global const int *pix_cell, int npix, int per,
                         volatile __global int *counts, __global int *pix_rank) {
    int a = get_global_id(0) * per;
    int e = min(npix, a + per);
    int pix = a;
    while (pix < e) {
        int cell = pix_cell[pix];
        int first = pix;
        while (pix < e && pix_cell[pix] == cell) ++pix;
        if (cell >= 0) {
            int base = atomic_add(&counts[cell], pix - first);
            for (int j = first; j < pix; ++j) pix_rank[j] = base + (j - first);
        }
    }
}

// Points per camera: each work-item counts the surviving pixels of `per` pixels of camera cami.w.
__kernel void count_camera(__global const int *pix_cell, int4 cami, int per, volatile __global int *cam_counts) {
    int a = get_global_id(0) * per, e = min(a + per, cami.y);
    int n = 0;
    for (int i = a; i < e; ++i) n += pix_cell[cami.x + i] >= 0;
    if (n) atomic_add(&cam_counts[cami.w], n);
}

// Exclusive scan of counts[0..n) into start[0..n], in nchunks chunks of `chunk` cells.
__kernel void scan_chunks(__global const int *counts, int n, int chunk,
                          __global int *start, __global int *partial) {
    int g = get_global_id(0);
    int a = g * chunk, b = min(n, a + chunk);
    int s = 0;
    for (int i = a; i < b; ++i) { start[i] = s; s += counts[i]; }
    partial[g] = s;
}

__kernel void scan_partials(__global int *partial, int nchunks, __global int *start, int n) {
    if (get_global_id(0) != 0) return;
    int s = 0;
    for (int g = 0; g < nchunks; ++g) { int v = partial[g]; partial[g] = s; s += v; }
    start[n] = s;
}

__kernel void scan_add(__global int *start, int n, int chunk, __global const int *partial) {
    int g = get_global_id(0);
    int a = g * chunk, b = min(n, a + chunk);
    int off = partial[g];
    for (int i = a; i < b; ++i) start[i] += off;
}

// Entry of every surviving pixel into its cell's slot range.
__kernel void scatter(__global const int *pix_cell, __global const int *pix_rank, __global const uchar *pix_prot,
                      int npix, __global const int *start, __global int *order) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (cell < 0) return;
    order[start[cell] + pix_rank[pix]] = pix | ((int)pix_prot[pix] << 31);
}

// Pixel index of an order entry (bit 31 holds the protected flag).
inline int entry_pixel(int e) { return e & 0x7fffffff; }

// Max-heap sift-down of o[i] within o[0 .. n), keyed by pixel.
inline void sift_down(__global int *o, int i, int n) {
    int v = o[i], kv = entry_pixel(v);
    for (;;) {
        int ch = 2 * i + 1;
        if (ch >= n) break;
        int kc = entry_pixel(o[ch]);
        if (ch + 1 < n) {
            int k2 = entry_pixel(o[ch + 1]);
            if (k2 > kc) { ++ch; kc = k2; }
        }
        if (kc <= kv) break;
        o[i] = o[ch];
        i = ch;
    }
    o[i] = v;
}

// Most stretches of one cell sort_cells orders by their first pixel; a cell cut into more (cells
// alternating pixel by pixel) is heapsorted instead.
#define SORT_STRETCHES 256

// Every cell's entries into ascending pixel order, in place in `order`, one work-item per cell.
// Pixels are unique, so the result does not depend on the order the scatter left (deterministic
// by construction). The scatter leaves a cell's entries as stretches of consecutive pixels (one
// atomic a run of equal cells in count_runs, a run being an interval of pixels); stretches of one
// cell are disjoint intervals, so ordering them by their first pixel and copying each in turn
// gives the pixel order: O(n) a cell plus an insertion sort of the stretches (they arrive nearly
// in order). The stretches' starts are listed in the cell's slot range of `starts` (count_runs'
// ranks, which the scatter has read), in global memory: a private list a work-item would be
// replicated for every work-item of PoCL's work-groups. A cell already in order is left alone;
// another is copied to its slot range of `scratch` and written back stretch by stretch. A cell of
// more than SORT_STRETCHES stretches is heapsorted in place (O(n log n), whatever the order).
__kernel void sort_cells(__global const int *start, int ncells, __global int *order, __global int *starts,
                         __global int *scratch) {
    int c = get_global_id(0);
    if (c >= ncells) return;
    int a = start[c], n = start[c + 1] - a;
    if (n < 2) return;
    __global int *o = order + a;
    __global int *at = starts + a;                 // stretch starts (indices into o), by first pixel
    int m = 0, prev = -2, moved = 0;
    for (int i = 0; i < n; ++i) {
        int p = entry_pixel(o[i]);
        if (p != prev + 1) {                       // a new stretch starts at i
            if (m == SORT_STRETCHES) { ++m; break; }
            int j = m++;                           // insertion by first pixel
            while (j > 0 && entry_pixel(o[at[j - 1]]) > p) { at[j] = at[j - 1]; --j; }
            moved |= j != m - 1;
            at[j] = i;
        }
        prev = p;
    }
    if (m <= SORT_STRETCHES) {
        if (!moved) return;                        // already in pixel order
        __global int *src = scratch + a;
        for (int i = 0; i < n; ++i) src[i] = o[i];
        int k = 0;
        for (int s = 0; s < m; ++s) {
            int i = at[s], p = entry_pixel(src[i]);
            do { o[k++] = src[i++]; } while (i < n && entry_pixel(src[i]) == ++p);
        }
        return;
    }
    for (int i = n / 2 - 1; i >= 0; --i) sift_down(o, i, n);
    for (int end = n - 1; end > 0; --end) {
        int t = o[0]; o[0] = o[end]; o[end] = t;
        sift_down(o, 0, end);
    }
}

// ---- motion estimation (kernels/motion.py) ----------------------------------------------------
// Per cell: number of points, sums of x, y, z and of xx, xy, xz, yy, yz, zz (10 floats per
// cell), in coordinates relative to the cell's lower corner (small numbers: float32 sums).
__kernel void cell_moments(__global const float4 *pts, __global const int *order, __global const int *start,
                           float4 grid, int4 dims, __global float *mom) {
    int c = get_global_id(0);
    int ncells = dims.x * dims.y * dims.z;
    if (c >= ncells) return;
    float h = 1.0f / grid.w;
    int ix = c % dims.x, iy = (c / dims.x) % dims.y, iz = c / (dims.x * dims.y);
    float ox = grid.x + ix * h, oy = grid.y + iy * h, oz = grid.z + iz * h;
    int a = start[c], e = start[c + 1];
    float s[9] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    for (int i = a; i < e; ++i) {
        float4 p = pts[order[i] & 0x7fffffff];
        float x = p.x - ox, y = p.y - oy, z = p.z - oz;
        s[0] += x; s[1] += y; s[2] += z;
        s[3] += x * x; s[4] += x * y; s[5] += x * z; s[6] += y * y; s[7] += y * z; s[8] += z * z;
    }
    __global float *m = mom + (size_t)c * 10;
    m[0] = (float)(e - a);
    for (int k = 0; k < 9; ++k) m[k + 1] = s[k];
}

// Every point's velocity, in the cell-sorted order of `order`, from its cell's motion (4 float4
// per cell: velocity at the cell's lower corner, then the rows of its gradient W):
// v + W (p - corner), in the reference's order of operations (motion.expand), no contraction.
__kernel void expand_velocity(__global const float4 *cell_motion, __global const float4 *pts,
                              __global const int *order, __global const int *start, float4 grid, int4 dims,
                              __global float4 *vel) {
    #pragma OPENCL FP_CONTRACT OFF
    int c = get_global_id(0);
    int ncells = dims.x * dims.y * dims.z;
    if (c >= ncells) return;
    float h = 1.0f / grid.w;
    int ix = c % dims.x, iy = (c / dims.x) % dims.y, iz = c / (dims.x * dims.y);
    float ox = grid.x + ix * h, oy = grid.y + iy * h, oz = grid.z + iz * h;
    float4 v = cell_motion[4 * c], w0 = cell_motion[4 * c + 1], w1 = cell_motion[4 * c + 2],
           w2 = cell_motion[4 * c + 3];
    for (int i = start[c]; i < start[c + 1]; ++i) {
        float4 p = pts[order[i] & 0x7fffffff];
        float x = p.x - ox, y = p.y - oy, z = p.z - oz;
        float a = w0.x * x, b = w0.y * y, e = w0.z * z;
        float vx = v.x + ((a + b) + e);
        a = w1.x * x; b = w1.y * y; e = w1.z * z;
        float vy = v.y + ((a + b) + e);
        a = w2.x * x; b = w2.y * y; e = w2.z * z;
        float vz = v.z + ((a + b) + e);
        vel[i] = (float4)(vx, vy, vz, 0.0f);
    }
}
