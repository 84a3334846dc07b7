/* A minimal JSON reader for the test vectors (objects, arrays, strings without escapes other than
 * \" and \\, numbers, true/false/null). Nodes live in a fixed pool; values point into the text. */
#ifndef MINIJSON_H
#define MINIJSON_H
#include <stdint.h>
#if defined(__GNUC__)
#pragma GCC diagnostic ignored "-Wunused-function"
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { J_NULL, J_BOOL, J_NUM, J_STR, J_ARR, J_OBJ };
typedef struct jnode { int type; const char *s; size_t n; const char *key; size_t keyn; int child, next; } jnode;

#define J_POOL 200000
static jnode j_pool[J_POOL];
static int j_used;
static const char *j_p;

static void j_ws(void) { while (*j_p == ' ' || *j_p == '\n' || *j_p == '\r' || *j_p == '\t') j_p++; }
static int j_new(int type) {
    if (j_used >= J_POOL) { fprintf(stderr, "json: pool full\n"); exit(2); }
    memset(&j_pool[j_used], 0, sizeof(jnode));
    j_pool[j_used].type = type; j_pool[j_used].child = j_pool[j_used].next = -1;
    return j_used++;
}
static int j_value(void);
static int j_string(const char **s, size_t *n) {
    if (*j_p != '"') return -1;
    *s = ++j_p;
    while (*j_p && *j_p != '"') { if (*j_p == '\\') j_p++; j_p++; }
    if (*j_p != '"') return -1;
    *n = (size_t)(j_p - *s);
    j_p++;
    return 0;
}
static int j_value(void) {
    int id, last = -1;
    j_ws();
    if (*j_p == '{' || *j_p == '[') {
        int obj = *j_p == '{';
        id = j_new(obj ? J_OBJ : J_ARR);
        j_p++; j_ws();
        if (*j_p == (obj ? '}' : ']')) { j_p++; return id; }
        for (;;) {
            const char *k = NULL; size_t kn = 0; int c;
            j_ws();
            if (obj) { if (j_string(&k, &kn)) return -1; j_ws(); if (*j_p++ != ':') return -1; }
            c = j_value();
            if (c < 0) return -1;
            j_pool[c].key = k; j_pool[c].keyn = kn;
            if (last < 0) j_pool[id].child = c; else j_pool[last].next = c;
            last = c;
            j_ws();
            if (*j_p == ',') { j_p++; continue; }
            if (*j_p == (obj ? '}' : ']')) { j_p++; return id; }
            return -1;
        }
    }
    if (*j_p == '"') { id = j_new(J_STR); return j_string(&j_pool[id].s, &j_pool[id].n) ? -1 : id; }
    if (!strncmp(j_p, "true", 4) || !strncmp(j_p, "false", 5)) {
        id = j_new(J_BOOL); j_pool[id].s = j_p; j_pool[id].n = *j_p == 't' ? 4 : 5; j_p += j_pool[id].n; return id;
    }
    if (!strncmp(j_p, "null", 4)) { j_p += 4; return j_new(J_NULL); }
    id = j_new(J_NUM); j_pool[id].s = j_p;
    while (*j_p && strchr("+-0123456789.eE", *j_p)) j_p++;
    j_pool[id].n = (size_t)(j_p - j_pool[id].s);
    return j_pool[id].n ? id : -1;
}
static char *j_text;
static int j_load(const char *path) {
    FILE *f = fopen(path, "rb"); long len;
    if (!f) { fprintf(stderr, "cannot open %s\n", path); exit(2); }
    fseek(f, 0, SEEK_END); len = ftell(f); fseek(f, 0, SEEK_SET);
    free(j_text);
    j_text = (char *)malloc((size_t)len + 1);
    if (fread(j_text, 1, (size_t)len, f) != (size_t)len) { fprintf(stderr, "read %s\n", path); exit(2); }
    j_text[len] = 0; fclose(f);
    j_used = 0; j_p = j_text;
    { int root = j_value(); if (root < 0) { fprintf(stderr, "json: parse error in %s\n", path); exit(2); } return root; }
}
static int j_get(int obj, const char *key) {
    int c;
    for (c = j_pool[obj].child; c >= 0; c = j_pool[c].next)
        if (j_pool[c].keyn == strlen(key) && !strncmp(j_pool[c].key, key, j_pool[c].keyn)) return c;
    fprintf(stderr, "json: no key %s\n", key); exit(2);
}
static int j_has(int obj, const char *key) {
    int c;
    for (c = j_pool[obj].child; c >= 0; c = j_pool[c].next)
        if (j_pool[c].keyn == strlen(key) && !strncmp(j_pool[c].key, key, j_pool[c].keyn)) return 1;
    return 0;
}
static int j_at(int arr, int i) { int c = j_pool[arr].child; while (c >= 0 && i--) c = j_pool[c].next; return c; }
static int j_count(int arr) { int n = 0, c; for (c = j_pool[arr].child; c >= 0; c = j_pool[c].next) n++; return n; }
static double j_num(int id) { char b[64]; size_t n = j_pool[id].n < 63 ? j_pool[id].n : 63; memcpy(b, j_pool[id].s, n); b[n] = 0; return strtod(b, NULL); }
static uint64_t j_u64(int id) { char b[64]; size_t n = j_pool[id].n < 63 ? j_pool[id].n : 63; memcpy(b, j_pool[id].s, n); b[n] = 0; return strtoull(b, NULL, 10); }
static int j_bool(int id) { return j_pool[id].type == J_BOOL && j_pool[id].s[0] == 't'; }
static void j_str(int id, char *out, size_t cap) { size_t n = j_pool[id].n < cap - 1 ? j_pool[id].n : cap - 1; memcpy(out, j_pool[id].s, n); out[n] = 0; }
static size_t j_hex(int id, uint8_t *out, size_t cap) {
    size_t i, n = j_pool[id].n / 2;
    if (n > cap) { fprintf(stderr, "json: hex too long\n"); exit(2); }
    for (i = 0; i < n; i++) { unsigned v; sscanf(j_pool[id].s + 2 * i, "%2x", &v); out[i] = (uint8_t)v; }
    return n;
}
static double j_numat(int obj, const char *key, int i) { return j_num(j_at(j_get(obj, key), i)); }
#endif
