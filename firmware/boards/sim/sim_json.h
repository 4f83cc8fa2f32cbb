/*
 * sim_json.h - a small JSON reader and writer for the simulator's control channel.
 *
 * Reader: parses one JSON text in place (strings are unescaped into the input buffer)
 * into a fixed pool of nodes; no allocation. Writer: appends to a growable buffer.
 */
#ifndef SIM_JSON_H
#define SIM_JSON_H

#include <stddef.h>
#include <stdint.h>

typedef enum { SJ_NULL, SJ_BOOL, SJ_NUM, SJ_STR, SJ_ARR, SJ_OBJ } sj_type_t;

typedef struct sj_node {
    sj_type_t type;
    double num;        /* SJ_NUM; SJ_BOOL: 0/1 */
    const char *str;   /* SJ_STR: NUL-terminated, unescaped */
    const char *key;   /* member name when the parent is an object */
    int first;         /* first child (array/object), -1 none */
    int next;          /* next sibling, -1 none */
    int count;         /* number of children */
} sj_node_t;

#define SJ_MAX_NODES 512

typedef struct sj_doc {
    sj_node_t nodes[SJ_MAX_NODES];
    int n;
    const char *error; /* set when parsing fails */
} sj_doc_t;

/* Parse text (modified in place). Returns the root node index or -1 (doc->error). */
int sj_parse(sj_doc_t *d, char *text);

/* Member `key` of object node `obj`, -1 if absent or obj is not an object. */
int sj_get(const sj_doc_t *d, int obj, const char *key);
/* Element i of array node `arr`, -1 if absent. */
int sj_at(const sj_doc_t *d, int arr, int i);

/* ---- writer ---- */
typedef struct sj_buf {
    char *p;
    size_t len, cap;
    int oom;
} sj_buf_t;

void sj_buf_free(sj_buf_t *b);
void sj_raw(sj_buf_t *b, const char *s);
void sj_printf(sj_buf_t *b, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
void sj_str(sj_buf_t *b, const char *s);               /* quoted, escaped */
void sj_num(sj_buf_t *b, double v);                    /* null when not finite */
void sj_vec(sj_buf_t *b, const double *v, int n);      /* [a, b, c] */
/* "key": prefixes; they add a comma unless the buffer ends with '{' or '['. */
void sj_key(sj_buf_t *b, const char *key);

#endif
