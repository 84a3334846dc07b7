"""Frame pipeline and spatial-hash build as Warp kernels. Mirrors kernels/opencl/frames.cl.

Snapshot layout (as the OpenCL backend): ``pts[pix] = (x, y, z, r_f)`` and ``sigma[pix]`` in
pixel order; ``order[start[c]:start[c+1]]`` = entries of cell c, entry = pix | protected << 31,
in ascending pixel order within the cell (a stable radix sort of the pixels by cell,
``wp.utils.radix_sort_pairs``: the same order on every run and backend, the reference's); plus ``sorted_pts``, the points in ``order``'s order (the GPU reads
them coalesced).
"""
from __future__ import annotations

import warp as wp


@wp.struct
class CamArgs:
    """One camera of the rig for one frame: pose, depth conversion, noise, validity."""

    R: wp.mat33  # camera -> world rotation
    t: wp.vec3  # camera -> world translation, m
    offset: int  # first pixel of this camera in the rig
    n: int  # pixels
    index: int  # camera id
    max_code: wp.uint32
    depth_scale: float
    bias_a: float  # a reading z is taken at z - max(bias_a, bias_b z^2) (Camera.near_bias; 0, 0: as read)
    bias_b: float
    z_min: float
    z_max: float
    noise_a: float
    noise_b: float
    lateral: float  # lateral_px / min(fx, fy)
    has_color: int
    has_mask: int


@wp.struct
class GridArgs:
    wmin: wp.vec3
    wmax: wp.vec3
    origin: wp.vec3
    inv_h: float
    nx: int
    ny: int
    nz: int


@wp.struct
class SelectArgs:
    kind: int  # 0 all, 1 box, 2 colour, 3 mask
    box_min: wp.vec3
    box_max: wp.vec3
    lo: wp.vec3i
    hi: wp.vec3i
    r_base: float
    k_sigma: float
    r_max: float
    adaptive: int


@wp.func
def cell_coord(v: float, o: float, inv_h: float, n: int) -> int:
    c = int(wp.floor((v - o) * inv_h))
    return wp.clamp(c, 0, n - 1)


@wp.func
def sigma_max(sz: float, sl: float, rx: float, ry: float) -> float:
    """sqrt(lambda_max) of sz^2 r r^T + sl^2 (I - e_z e_z^T), r = (rx, ry, 1) (closed form)."""
    s2 = sz * sz
    l2 = sl * sl
    rho2 = rx * rx + ry * ry
    t = s2 * (1.0 + rho2)
    dd = t - l2
    return wp.sqrt(0.5 * (t + l2 + wp.sqrt(dd * dd + 4.0 * l2 * s2 * rho2)))


@wp.kernel
def classify(depth: wp.array(dtype=wp.uint16), rays: wp.array(dtype=wp.vec2), cams: wp.array(dtype=CamArgs),
             ci: int, g: GridArgs, sel: SelectArgs, color: wp.array(dtype=wp.uint8), mask: wp.array(dtype=wp.uint8),
             pix_cell: wp.array(dtype=int), pix_prot: wp.array(dtype=int), pts: wp.array(dtype=wp.vec4),
             sig: wp.array(dtype=float)):
    i = wp.tid()
    cam = cams[ci]
    if i >= cam.n:
        return
    pix = cam.offset + i
    d = wp.uint32(depth[pix])
    z = float(d) * cam.depth_scale
    z = z - wp.max(cam.bias_a, cam.bias_b * z * z)
    r = rays[pix]
    xc = r[0] * z
    yc = r[1] * z
    R = cam.R
    x = R[0, 0] * xc + R[0, 1] * yc + R[0, 2] * z + cam.t[0]
    y = R[1, 0] * xc + R[1, 1] * yc + R[1, 2] * z + cam.t[1]
    w = R[2, 0] * xc + R[2, 1] * yc + R[2, 2] * z + cam.t[2]
    ok = d != wp.uint32(0) and d != cam.max_code and z >= cam.z_min and z <= cam.z_max
    ok = ok and x >= g.wmin[0] and y >= g.wmin[1] and w >= g.wmin[2]
    ok = ok and x < g.wmax[0] and y < g.wmax[1] and w < g.wmax[2]
    if not ok:
        pix_cell[pix] = -1
        return
    ix = cell_coord(x, g.origin[0], g.inv_h, g.nx)
    iy = cell_coord(y, g.origin[1], g.inv_h, g.ny)
    iz = cell_coord(w, g.origin[2], g.inv_h, g.nz)
    pix_cell[pix] = (iz * g.ny + iy) * g.nx + ix
    sigma = sigma_max(cam.noise_a + cam.noise_b * z * z, cam.lateral * z, r[0], r[1])
    rf = sel.r_base
    if sel.adaptive != 0:
        rf = wp.min(sel.r_base + sel.k_sigma * sigma, sel.r_max)
    prot = int(1)
    if sel.kind == 1:
        inside = x >= sel.box_min[0] and y >= sel.box_min[1] and w >= sel.box_min[2]
        inside = inside and x <= sel.box_max[0] and y <= sel.box_max[1] and w <= sel.box_max[2]
        prot = wp.where(inside, 1, 0)
    elif sel.kind == 2:
        prot = 0
        if cam.has_color != 0:
            cr = int(color[3 * pix])
            cg = int(color[3 * pix + 1])
            cb = int(color[3 * pix + 2])
            inside = cr >= sel.lo[0] and cg >= sel.lo[1] and cb >= sel.lo[2]
            inside = inside and cr <= sel.hi[0] and cg <= sel.hi[1] and cb <= sel.hi[2]
            prot = wp.where(inside, 1, 0)
    elif sel.kind == 3:
        prot = 0
        if cam.has_mask != 0 and mask[pix] != wp.uint8(0):
            prot = 1
    pix_prot[pix] = prot
    pts[pix] = wp.vec4(x, y, w, rf)
    sig[pix] = sigma


@wp.kernel
def count_runs(pix_cell: wp.array(dtype=int), cam_of: wp.array(dtype=int), npix: int, per: int,
               counts: wp.array(dtype=int), cam_counts: wp.array(dtype=int)):
    """Count per cell and per camera, one atomic per run of same-cell pixels of one camera
    (each thread walks ``per`` consecutive pixels; neighbouring pixels mostly share a cell)."""
    a = wp.tid() * per
    e = wp.min(npix, a + per)
    pix = a
    while pix < e:
        cell = pix_cell[pix]
        cam = cam_of[pix]
        first = pix
        while pix < e and pix_cell[pix] == cell and cam_of[pix] == cam:
            pix += 1
        if cell >= 0:
            n = pix - first
            wp.atomic_add(counts, cell, n)
            wp.atomic_add(cam_counts, cam, n)


@wp.kernel
def scan_chunks(counts: wp.array(dtype=int), n: int, chunk: int, start: wp.array(dtype=int),
                partial: wp.array(dtype=int)):
    """Exclusive scan of counts[0..n) into start, chunk by chunk (as frames.cl)."""
    g = wp.tid()
    a = g * chunk
    b = wp.min(n, a + chunk)
    s = int(0)
    for i in range(a, b):
        start[i] = s
        s += counts[i]
    partial[g] = s


@wp.kernel
def scan_partials(partial: wp.array(dtype=int), nchunks: int, start: wp.array(dtype=int), n: int):
    s = int(0)
    for g in range(nchunks):
        v = partial[g]
        partial[g] = s
        s += v
    start[n] = s


@wp.kernel
def scan_add(start: wp.array(dtype=int), n: int, chunk: int, partial: wp.array(dtype=int)):
    g = wp.tid()
    a = g * chunk
    b = wp.min(n, a + chunk)
    off = partial[g]
    for i in range(a, b):
        start[i] = start[i] + off


@wp.kernel
def sort_input(pix_cell: wp.array(dtype=int), pix_prot: wp.array(dtype=int), n_cells: int,
               keys: wp.array(dtype=int), entries: wp.array(dtype=int)):
    """Each pixel's (cell, entry) pair in pixel order for the stable radix sort that builds
    ``order``; a pixel in no cell gets key ``n_cells`` (sorted past every cell)."""
    pix = wp.tid()
    cell = pix_cell[pix]
    e = pix
    if pix_prot[pix] != 0:
        e = pix | (-2147483647 - 1)
    if cell < 0:
        cell = n_cells
    keys[pix] = cell
    entries[pix] = e


@wp.func
def entry_pixel(e: int) -> int:
    """Pixel index of an order entry (bit 31 holds the protected flag)."""
    return e & 2147483647


@wp.kernel
def take_sorted(entries: wp.array(dtype=int), start: wp.array(dtype=int), n_cells: int, order: wp.array(dtype=int)):
    """The sorted entries of the pixels in a cell are ``order`` (the rest sorted past them)."""
    i = wp.tid()
    if i < start[n_cells]:
        order[i] = entries[i]


@wp.kernel
def gather_sorted(order: wp.array(dtype=int), start: wp.array(dtype=int), n_cells: int, pts: wp.array(dtype=wp.vec4),
                  sorted_pts: wp.array(dtype=wp.vec4)):
    """(GPU layout) the points in ``order``'s order, so that queries read consecutive points
    with one coalesced load instead of two dependent ones."""
    i = wp.tid()
    if i < start[n_cells]:
        sorted_pts[i] = pts[entry_pixel(order[i])]


@wp.kernel
def cell_moments(sorted_pts: wp.array(dtype=wp.vec4), start: wp.array(dtype=int), g: GridArgs,
                 mom: wp.array2d(dtype=float)):
    """Motion estimation (kernels/motion.py): per cell the number of points, the sums of x, y, z
    and of xx, xy, xz, yy, yz, zz, relative to the cell's lower corner."""
    c = wp.tid()
    h = 1.0 / g.inv_h
    ix = c % g.nx
    iy = (c / g.nx) % g.ny
    iz = c / (g.nx * g.ny)
    o = wp.vec3(g.origin[0] + float(ix) * h, g.origin[1] + float(iy) * h, g.origin[2] + float(iz) * h)
    a = start[c]
    e = start[c + 1]
    s = wp.vec3(0.0)
    sxx = float(0.0)
    sxy = float(0.0)
    sxz = float(0.0)
    syy = float(0.0)
    syz = float(0.0)
    szz = float(0.0)
    for i in range(a, e):
        q = sorted_pts[i]
        x = q[0] - o[0]
        y = q[1] - o[1]
        z = q[2] - o[2]
        s = s + wp.vec3(x, y, z)
        sxx += x * x
        sxy += x * y
        sxz += x * z
        syy += y * y
        syz += y * z
        szz += z * z
    mom[c, 0] = float(e - a)
    mom[c, 1] = s[0]
    mom[c, 2] = s[1]
    mom[c, 3] = s[2]
    mom[c, 4] = sxx
    mom[c, 5] = sxy
    mom[c, 6] = sxz
    mom[c, 7] = syy
    mom[c, 8] = syz
    mom[c, 9] = szz


@wp.kernel
def expand_velocity(cell_motion: wp.array(dtype=wp.vec4), sorted_pts: wp.array(dtype=wp.vec4),
                    start: wp.array(dtype=int), g: GridArgs, sorted_vel: wp.array(dtype=wp.vec4)):
    """Every sorted point's velocity from its cell's motion (kernels/motion.py ``CELL_MOTION``:
    4 vec4 per cell, the velocity at the cell's lower corner and the rows of its gradient W):
    v + W (p - corner)."""
    c = wp.tid()
    h = 1.0 / g.inv_h
    ix = c % g.nx
    iy = (c / g.nx) % g.ny
    iz = c / (g.nx * g.ny)
    o = wp.vec3(g.origin[0] + float(ix) * h, g.origin[1] + float(iy) * h, g.origin[2] + float(iz) * h)
    v = cell_motion[4 * c]
    w0 = cell_motion[4 * c + 1]
    w1 = cell_motion[4 * c + 2]
    w2 = cell_motion[4 * c + 3]
    for i in range(start[c], start[c + 1]):
        q = sorted_pts[i]
        x = q[0] - o[0]
        y = q[1] - o[1]
        z = q[2] - o[2]
        sorted_vel[i] = wp.vec4(v[0] + ((w0[0] * x + w0[1] * y) + w0[2] * z),
                                v[1] + ((w1[0] * x + w1[1] * y) + w1[2] * z),
                                v[2] + ((w2[0] * x + w2[1] * y) + w2[2] * z), 0.0)
