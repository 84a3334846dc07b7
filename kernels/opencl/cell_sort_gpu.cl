// The GPU-shaped cell sort of a snapshot (kernels/opencl/cell_sort.py says how it works): runs of
// one cell listed by their heads, then ordered by their heads alone. Inputs are classify's
// (frames.cl): pix_cell[pix] (-1: no point) and pix_prot[pix] for every rig pixel. Output:
// order[start[c] .. start[c+1]) = entries of cell c in ascending pixel order, entry = pix | protected << 31.
// counts holds 2 ncells ints, zero on entry: counts[c], the points of cell c (scanned into start),
// then counts[ncells + c], the runs of cell c.

// Longest run: a run never crosses a multiple of RUN_MAX pixels, which bounds a head's walk in
// count_heads and its copy in order_runs.
#define RUN_MAX 64

// Whether pixel `pix` of cell `cell` starts a run: it has a point, and it starts a RUN_MAX block or
// its left neighbour in rig pixel order lies in another cell (or has no point).
inline int run_head(__global const int *pix_cell, int pix, int cell) {
    return cell >= 0 && (pix % RUN_MAX == 0 || pix_cell[pix - 1] != cell);
}

// Every run's length, its points counted into its cell, and its index among its cell's runs (in
// the order the atomics came: order_runs does not depend on it).
__kernel void count_heads(__global const int *pix_cell, int npix, int ncells, volatile __global int *counts,
                          __global int *run_slot, __global int *run_len) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int end = min(npix, (pix / RUN_MAX + 1) * RUN_MAX);
    int e = pix + 1;
    while (e < end && pix_cell[e] == cell) ++e;
    run_len[pix] = e - pix;
    atomic_add(&counts[cell], e - pix);
    run_slot[pix] = atomic_inc(&counts[ncells + cell]);
}

// The list of each cell's runs, (head pixel, length) at start[c] + the run's index: a cell has
// no more runs than points, so its list fits in its own slot range.
__kernel void place_heads(__global const int *pix_cell, int npix, __global const int *start,
                          __global const int *run_slot, __global const int *run_len,
                          __global int *head_pix, __global int *head_len) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int s = start[cell] + run_slot[pix];
    head_pix[s] = pix;
    head_len[s] = run_len[pix];
}

// Each run's entries at their place in pixel order: the run's offset in its cell is the length of
// the cell's runs that start at a smaller pixel (runs of one cell are disjoint pixel intervals),
// whatever order the atomics listed them in.
__kernel void order_runs(__global const int *pix_cell, __global const uchar *pix_prot, int npix, int ncells,
                         __global const int *counts, __global const int *start, __global const int *head_pix,
                         __global const int *head_len, __global const int *run_len, __global int *order) {
    int pix = get_global_id(0);
    if (pix >= npix) return;
    int cell = pix_cell[pix];
    if (!run_head(pix_cell, pix, cell)) return;
    int a = start[cell], nruns = counts[ncells + cell];
    int rank = 0;
    for (int j = a; j < a + nruns; ++j) rank += head_pix[j] < pix ? head_len[j] : 0;
    int n = run_len[pix];
    __global int *o = order + a + rank;
    for (int k = 0; k < n; ++k) o[k] = (pix + k) | ((int)pix_prot[pix + k] << 31);
}
