// Fixed-radius neighbours in the spatial hash, shaped for CPUs: one work-item per query.
// Mirrors kernels/reference/neighbors.py (neighbors_gpu.cl: the GPU shape, same results).
// Snapshot layout (frames.cl): pts in pixel order, order[] = pix | protected << 31 sorted by cell.
// Reported indices are positions in `order` (the host snapshot's point indices).
#pragma OPENCL FP_CONTRACT OFF

__kernel void neighbors(__global const float4 *pts, __global const int *order, __global const int *start,
                        float4 grid, int4 dims, __global const float4 *queries, int nq,
                        float radius, int span, int K, int protected_only,
                        __global int *res) {
    // res: [count (nq)][nearest (nq)][bits of its distance, m (nq)][first K hits of each query (nq K)]
    int b = get_global_id(0);
    if (b >= nq) return;
    float4 q = queries[b];
    int cx = (int)clamp(floor((q.x - grid.x) * grid.w), (float)(-span - 1), (float)(dims.x + span));
    int cy = (int)clamp(floor((q.y - grid.y) * grid.w), (float)(-span - 1), (float)(dims.y + span));
    int cz = (int)clamp(floor((q.z - grid.z) * grid.w), (float)(-span - 1), (float)(dims.z + span));
    int x0 = max(cx - span, 0), x1 = min(cx + span, dims.x - 1);
    int y0 = max(cy - span, 0), y1 = min(cy + span, dims.y - 1);
    int z0 = max(cz - span, 0), z1 = min(cz + span, dims.z - 1);
    float r2 = radius * radius;
    int n = 0, best = -1;
    float best_d2 = INFINITY;
    __global int *idx = res + 3 * nq + (size_t)b * K;
    for (int iz = z0; iz <= z1; ++iz)
        for (int iy = y0; iy <= y1; ++iy) {
            int base = (iz * dims.y + iy) * dims.x;
            int a = start[base + x0], e = start[base + x1 + 1];
            for (int i = a; i < e; ++i) {
                int entry = order[i];
                if (protected_only && entry >= 0) continue;
                float4 p = pts[entry & 0x7fffffff];
                float dx = p.x - q.x, dy = p.y - q.y, dz = p.z - q.z;
                float d2 = dx * dx + dy * dy + dz * dz;
                if (d2 <= r2) {
                    if (n < K) idx[n] = i;
                    ++n;
                    if (d2 < best_d2) { best_d2 = d2; best = i; }
                }
            }
        }
    for (int j = n; j < K; ++j) idx[j] = -1;
    res[b] = n;
    res[nq + b] = best;
    res[2 * nq + b] = as_int(best >= 0 ? sqrt(best_d2) : INFINITY);
}
