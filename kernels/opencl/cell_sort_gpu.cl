// The GPU-shaped cell sort of a snapshot (kernels/opencl/cell_sort.py says how it works): runs of
// one cell filed by their heads, then ordered by their heads alone. Inputs are classify's
// (frames.cl): pix_cell[pix] (-1: no point) and pix_prot[pix] for every rig pixel. Output:
// order[start[c] .. start[c+1]) = entries of cell c in ascending pixel order, entry = pix | protected << 31.

// Longest run: a run never crosses a multiple of RUN_MAX pixels, which bounds a head's walk in
// count_heads and its copy in order_runs (and the runs of one cell below npix / RUN_MAX + rows).
#define RUN_MAX 64

// Whether pixel `pix` of cell `cell` starts a run: it has a point, and it starts a RUN_MAX block or
// its left neighbour in rig pixel order lies in another cell (or has no point).
inline int run_head(__global const int *pix_cell, int pix, int cell) {
    return cell >= 0 && (pix % RUN_MAX == 0 || pix_cell[pix - 1] != cell);
}

// Every run's length and its slot range in its cell (one atomic a run: the ranges' order within
// a cell follows the atomics' order, which order_runs undoes). counts must be zero on entry.
__kernel void count_heads(__global const int *pix_cell, int npix, volatile __global int *counts,
                          __global int *run_base, __global int *run_len) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int end = min(npix, (pix / RUN_MAX + 1) * RUN_MAX);
    int e = pix + 1;
    while (e < end && pix_cell[e] == cell) ++e;
    run_len[pix] = e - pix;
    run_base[pix] = atomic_add(&counts[cell], e - pix);
}

// Each run's head pixel and length at the first slot of its range (start: the exclusive scan of
// counts). The ranges tile each cell's slots, so from start[c], seg_len jumps from head to head.
__kernel void place_heads(__global const int *pix_cell, int npix, __global const int *start,
                          __global const int *run_base, __global const int *run_len,
                          __global int *seg_pix, __global int *seg_len) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int s = start[cell] + run_base[pix];
    seg_pix[s] = pix;
    seg_len[s] = run_len[pix];
}

// Each run's entries at their place in pixel order: the run's offset in its cell is the length of
// the cell's runs that start at a smaller pixel (runs of one cell are disjoint pixel intervals),
// whatever order the atomics left the heads in.
__kernel void order_runs(__global const int *pix_cell, __global const uchar *pix_prot, int npix,
                         __global const int *start, __global const int *seg_pix, __global const int *seg_len,
                         __global const int *run_len, __global int *order) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int a = start[cell], e = start[cell + 1];
    int rank = 0;
    for (int j = a; j < e;) {
        int n = seg_len[j];
        if (seg_pix[j] < pix) rank += n;
        j += max(n, 1);   // (n >= 1 by construction; never loop on a bad length)
    }
    int n = run_len[pix];
    __global int *o = order + a + rank;
    for (int k = 0; k < n; ++k) o[k] = (pix + k) | ((int)pix_prot[pix + k] << 31);
}
