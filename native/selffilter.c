/* The robot self-filter's per-capsule pixel test (kernels/selffilter.py, SelfFilter.mask).
 *
 * Called through ctypes.CDLL: the interpreter lock is released while it runs, so a frame
 * thread filtering a frame never keeps the 1 kHz haptic loop waiting for the lock (the NumPy
 * version held it for 0.5 ms per frame at the median, 2 ms at p99, on a 2-core machine).
 *
 * Arithmetic: float64, evaluated as written (built with -ffp-contract=off), in the order of
 * the NumPy reference (selffilter.segment_distance), so both mark the same pixels. */
#include <math.h>
#include <stdint.h>

/* Marks (sets to 1) every pixel in rows [r0, r1) and columns [c0, c1) of an image of width
 * `width` whose depth reading d != 0 measures the point p = ray * (d * scale) (camera frame,
 * m; `rays` (H, W, 3) with z = 1) within `reach` (m) of the segment a-b (camera frame, m).
 * `depth` (H, W) uint16 and `mask` (H, W) uint8 are C-contiguous. Returns the pixels marked
 * (already marked ones included). */
int64_t pf_selffilter_capsule(const uint16_t *depth, const double *rays, int64_t width, int64_t r0, int64_t r1,
                              int64_t c0, int64_t c1, double scale, const double *a, const double *b, double reach,
                              uint8_t *mask)
{
    const double ab0 = b[0] - a[0], ab1 = b[1] - a[1], ab2 = b[2] - a[2];
    const double L2 = ab0 * ab0 + ab1 * ab1 + ab2 * ab2;
    int64_t marked = 0;
    for (int64_t r = r0; r < r1; ++r) {
        const uint16_t *drow = depth + r * width;
        const double *rrow = rays + r * width * 3;
        uint8_t *mrow = mask + r * width;
        for (int64_t c = c0; c < c1; ++c) {
            const uint16_t d = drow[c];
            if (d == 0)
                continue;
            const double z = (double)d * scale;
            const double *ray = rrow + c * 3;
            const double p0 = ray[0] * z, p1 = ray[1] * z, p2 = ray[2] * z;
            double t = 0.0;
            if (L2 != 0.0) {
                t = ((p0 - a[0]) * ab0 + (p1 - a[1]) * ab1 + (p2 - a[2]) * ab2) / L2;
                t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
            }
            const double e0 = p0 - (a[0] + t * ab0), e1 = p1 - (a[1] + t * ab1), e2 = p2 - (a[2] + t * ab2);
            if (sqrt(e0 * e0 + e1 * e1 + e2 * e2) <= reach) {
                mrow[c] = 1;
                ++marked;
            }
        }
    }
    return marked;
}
