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

/* Copies the `nf` fields `f` into row `i` of the ring `base` (rows of `width` float64s). */
void pf_row_gather(const pf_row_field *f, int64_t nf, double *base, int64_t width, int32_t i) {
    double *row = base + width * (int64_t)i;
    for (int64_t j = 0; j < nf; j++) {
        double *d = row + f[j].col;
        int32_t k = f[j].count;
        switch (f[j].kind) {
        case PF_ROW_F64: {
            const double *s = (const double *)f[j].src;
            for (int32_t c = 0; c < k; c++) d[c] = s[c];
            break;
        }
        case PF_ROW_U8: {
            const uint8_t *s = (const uint8_t *)f[j].src;
            for (int32_t c = 0; c < k; c++) d[c] = (double)s[c];
            break;
        }
        case PF_ROW_I64: {
            const int64_t *s = (const int64_t *)f[j].src;
            for (int32_t c = 0; c < k; c++) d[c] = (double)s[c];
            break;
        }
        case PF_ROW_I32: {
            const int32_t *s = (const int32_t *)f[j].src;
            for (int32_t c = 0; c < k; c++) d[c] = (double)s[c];
            break;
        }
        case PF_ROW_F32: {
            const float *s = (const float *)f[j].src;
            for (int32_t c = 0; c < k; c++) d[c] = (double)s[c];
            break;
        }
        default:
            break;
        }
    }
}
