/* A tick's row of a recording: every TickInput and TickOutput field copied into one float64 row
 * of a ring (service/tick_cdr.py, TickRows), in one call.
 *
 * The row's layout is service/tick_cdr.py's TickLayout; TickRows binds, once, one descriptor a
 * field: where its values are (a NumPy array of the struct, or a slot of the staging array that
 * holds the struct's scalars), how many and of which type, and the row's first column for them.
 * float64 holds every value exactly (bools, int32 contact states, int64 hold bits below 2^53).
 */
#include <stdint.h>

enum { PF_ROW_F64 = 0, PF_ROW_U8 = 1, PF_ROW_I64 = 2, PF_ROW_I32 = 3, PF_ROW_F32 = 4 };

/* One field: `count` values of type `kind` at `src`, into columns col .. col + count - 1. */
typedef struct {
    const void *src;
    int64_t col;
    int32_t count;
    int32_t kind;
} pf_row_field;

/* the `k` values of type T at `src` into `d`, as doubles */
#define COPY_AS_DOUBLE(T, src, d, k)                                      \
    do {                                                                  \
        const T *s_ = (const T *)(src);                                   \
        for (int32_t c_ = 0; c_ < (k); c_++) (d)[c_] = (double)s_[c_];    \
    } while (0)

/* Copies the `nf` fields `f` into row `i` of the ring `base` (rows of `width` float64s). */
void pf_row_gather(const pf_row_field *f, int64_t nf, double *base, int64_t width, int32_t i) {
    double *row = base + width * (int64_t)i;
    for (int64_t j = 0; j < nf; j++) {
        double *d = row + f[j].col;
        int32_t k = f[j].count;
        switch (f[j].kind) {
        case PF_ROW_F64: COPY_AS_DOUBLE(double, f[j].src, d, k); break;
        case PF_ROW_U8: COPY_AS_DOUBLE(uint8_t, f[j].src, d, k); break;
        case PF_ROW_I64: COPY_AS_DOUBLE(int64_t, f[j].src, d, k); break;
        case PF_ROW_I32: COPY_AS_DOUBLE(int32_t, f[j].src, d, k); break;
        case PF_ROW_F32: COPY_AS_DOUBLE(float, f[j].src, d, k); break;
        default:
            break;
        }
    }
}
