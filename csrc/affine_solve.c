/* The compiled half of the shape-preserving pass (docs/MATH.md §15; affine_deformers/core/arap/ is the
 * numpy reference, affine_deformers/accel/arap.py the Python side):
 *
 *  - ak_spd_factor: L L^T = P A P^T for a sparse symmetric positive definite A given as a full CSR
 *    matrix. P: a nested-dissection ordering of A's graph (or the natural or a given one), then a
 *    postorder of the elimination tree. Symbolic: elimination tree and column counts in O(nnz(L)),
 *    supernodes (chains of columns with nested structures, merged with their parent when that adds few
 *    zeros). Numeric: multifrontal, a dense front per supernode assembled from A and the update
 *    matrices of its children (a stack, in postorder), factored with blocked updates.
 *  - ak_spd_solve: A x = b for b (n, k) row-major in place: forward and back substitution by supernode.
 *  - ak_arap_frame: the pass's frame: the right-hand side of the displacement form from the elements'
 *    blended maps and the field's positions, the solve, and the extra iterations (the rotation nearest
 *    the completed solved gradient times the blended stretch, kept with that stretch).
 *  - ak_spd_free.
 *
 * Nested dissection: a part of the graph is searched breadth-first from a pseudo-peripheral vertex
 * (a vertex of least degree in the last level of the previous search, while the depth grows); the
 * smallest level among those leaving at least a fifth of the part on either side is the separator,
 * trimmed to the vertices adjacent to the next level. The part below it, the part above it, then the
 * separator are numbered in that order and the two parts dissected in turn; parts of at most ND_LEAF
 * vertices, or only two levels deep, are numbered in reverse breadth-first order. A search that does
 * not reach the whole part splits off the connected piece it reached.
 *
 * Everything runs on the calling thread in a fixed order of operations, compiled with IEEE semantics
 * (the kernel's flags, tools/build_native.py): a factorisation and a frame give the same bits on every
 * run and build. A handle is used by one call at a time (its scratch is shared by the calls). */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "affine_internal.h"
#include "affine_kernel.h"

#pragma STDC FP_CONTRACT OFF

#define ND_LEAF 32
#define ND_TRIES 5
/* Relaxed supernodes: a child chain is merged into its parent supernode when the merged panel has at
 * most RELAX_ZEROS of its entries explicitly zero, or when both have at most RELAX_SMALL columns. */
#define RELAX_ZEROS 0.05
#define RELAX_SMALL 4
/* Pivot columns applied together to the rest of a front. */
#define FRONT_BLOCK 4
/* Newton's polar iteration: at most this many steps, stopping when a step moves Q by NEWTON_TOL |Q|;
 * POLAR_BLOCK elements at a time, structure of arrays. */
#define NEWTON_STEPS 24
#define NEWTON_TOL 1e-13
#define POLAR_BLOCK 64

enum { ORDER_NATURAL = 0, ORDER_NESTED_DISSECTION = 1, ORDER_GIVEN = 2 };
enum { ST_OK = 0, ST_MEMORY = 1, ST_NOT_SPD = 2, ST_INPUT = 3 };
/* info[] slots of ak_spd_factor */
enum { I_STATUS, I_NNZ_L, I_SUPERNODES, I_BYTES, I_PIVOT, I_STORED, I_FLOPS, I_MAX_FRONT, I_SLOTS };

typedef struct {
    int64_t n, n_super, bytes;
    int64_t *perm;  /* perm[k]: the original index of pivot k */
    int64_t *first; /* (n_super + 1): each supernode's first pivot */
    int64_t *rptr;  /* (n_super + 1) into rows */
    int32_t *rows;  /* each supernode's rows (pivot numbers): its own pivots, then those below, ascending */
    int64_t *vptr;  /* (n_super + 1) into val */
    double *val;    /* each supernode's panel of L, rows x columns, column-major */
    double *work;   /* 3n: permuted right-hand sides */
    double *block;  /* 3 x the largest supernode's rows: its gathered right-hand sides */
    double *rhs;    /* 3n: a frame's right-hand side */
    double *elem;   /* 18 per element (stretch, target) once a frame iterates */
    int64_t elem_cap;
} spd_factor;

static void *alloc(int64_t count, size_t size) { return malloc(count > 0 ? (size_t)count * size : 1); }

/* ------------------------------------------------------------------------------------------------
 * nested dissection */

typedef struct {
    const int64_t *xadj;
    const int32_t *adj;
    int64_t *stamp; /* the part a vertex belongs to now */
    int32_t *level;
    int64_t *queue;
} graph_ws;

/* Breadth-first search from root over the vertices stamped s (their level[] -1 on entry): queue[0..count)
 * in visiting order, level[] of each; returns count, *height = the last level. */
static int64_t bfs(graph_ws *g, int64_t s, int64_t root, int32_t *height) {
    int64_t head = 0, tail = 0;
    g->queue[tail++] = root;
    g->level[root] = 0;
    while (head < tail) {
        int64_t v = g->queue[head++];
        int32_t next = g->level[v] + 1;
        for (int64_t p = g->xadj[v]; p < g->xadj[v + 1]; p++) {
            int64_t u = g->adj[p];
            if (g->stamp[u] == s && g->level[u] < 0) {
                g->level[u] = next;
                g->queue[tail++] = u;
            }
        }
    }
    *height = g->level[g->queue[tail - 1]];
    return tail;
}

static int64_t degree(const graph_ws *g, int64_t v) { return g->xadj[v + 1] - g->xadj[v]; }

/* Levels of the part seg[0..size) (stamped s) from a pseudo-peripheral root; returns how many vertices the
 * search reached (fewer than size: the part is not connected). */
static int64_t rooted_levels(graph_ws *g, int64_t s, const int64_t *seg, int64_t size, int32_t *height) {
    int64_t root = seg[0];
    for (int64_t i = 1; i < size; i++)
        if (degree(g, seg[i]) < degree(g, root)) root = seg[i];
    int32_t best = -1, h = 0;
    int64_t count = 0;
    for (int attempt = 0; attempt < ND_TRIES; attempt++) {
        for (int64_t i = 0; i < size; i++) g->level[seg[i]] = -1;
        count = bfs(g, s, root, &h);
        if (count < size || h <= best) break;
        best = h;
        int64_t next = g->queue[count - 1];
        for (int64_t i = count - 1; i >= 0 && g->level[g->queue[i]] == h; i--)
            if (degree(g, g->queue[i]) < degree(g, next)) next = g->queue[i];
        root = next;
    }
    *height = h;
    return count;
}

/* The separator level: the smallest level leaving a fifth of the part on either side, else the median. */
static int32_t separator_level(const int64_t *counts, int32_t h, int64_t size) {
    int64_t below = 0, best = -1;
    int32_t best_k = -1, median = -1;
    for (int32_t k = 1; k < h; k++) {
        below += counts[k - 1];
        int64_t above = size - below - counts[k];
        if (5 * below >= size && 5 * above >= size && (best < 0 || counts[k] < best)) {
            best = counts[k];
            best_k = k;
        }
        if (median < 0 && 2 * (below + counts[k]) >= size) median = k;
    }
    if (best_k >= 0) return best_k;
    if (median < 1) median = 1;
    return median < h ? median : h - 1;
}

/* Splits the connected part seg (levels from its root, in queue order) into [below | above | separator]
 * via tmp; returns the sizes of the first two through n_below and n_above. */
static void dissect(graph_ws *g, int64_t s, int64_t *seg, int64_t size, int32_t h, int64_t *counts, int64_t *tmp,
                    int64_t *n_below, int64_t *n_above) {
    for (int32_t k = 0; k <= h; k++) counts[k] = 0;
    for (int64_t i = 0; i < size; i++) counts[g->level[g->queue[i]]]++;
    int32_t k = separator_level(counts, h, size);
    /* the separator: level-k vertices next to level k + 1 (the others join the part below); marked -2 */
    int64_t n_sep = 0;
    for (int64_t i = 0; i < size; i++) {
        int64_t v = g->queue[i];
        if (g->level[v] != k) continue;
        for (int64_t p = g->xadj[v]; p < g->xadj[v + 1]; p++) {
            int64_t u = g->adj[p];
            if (g->stamp[u] == s && g->level[u] == k + 1) {
                tmp[size - 1 - n_sep++] = v; /* filled from the end, reversed below */
                break;
            }
        }
    }
    for (int64_t i = 0; i < n_sep; i++) g->level[tmp[size - 1 - i]] = -2;
    int64_t a = 0, b = 0;
    for (int64_t i = 0; i < size; i++) {
        int32_t lv = g->level[g->queue[i]];
        if (lv >= 0 && lv <= k) tmp[a++] = g->queue[i];
    }
    for (int64_t i = 0; i < size; i++)
        if (g->level[g->queue[i]] > k) tmp[a + b++] = g->queue[i];
    for (int64_t i = 0; i < n_sep; i++) seg[a + b + i] = tmp[size - 1 - i];
    memcpy(seg, tmp, (size_t)(a + b) * sizeof *seg);
    *n_below = a;
    *n_above = b;
}

/* order[k] = the vertex numbered k. Returns 0, or -1 when out of memory. */
static int nested_dissection(int64_t n, const int64_t *xadj, const int32_t *adj, int64_t *order) {
    graph_ws g = {xadj, adj, alloc(n, sizeof(int64_t)), alloc(n, sizeof(int32_t)), alloc(n, sizeof(int64_t))};
    int64_t *tmp = alloc(n, sizeof(int64_t)), *counts = alloc(n + 1, sizeof(int64_t));
    int64_t *stack = alloc(2 * (n + 1), sizeof(int64_t));
    int ok = g.stamp && g.level && g.queue && tmp && counts && stack;
    if (ok) {
        for (int64_t v = 0; v < n; v++) {
            order[v] = v;
            g.stamp[v] = -1;
        }
        int64_t sp = 0, s = 0;
        if (n > 0) {
            stack[sp++] = 0;
            stack[sp++] = n;
        }
        while (sp > 0) {
            int64_t hi = stack[--sp], lo = stack[--sp], size = hi - lo;
            int64_t *seg = order + lo;
            s++;
            for (int64_t i = 0; i < size; i++) g.stamp[seg[i]] = s;
            int32_t h;
            int64_t count = rooted_levels(&g, s, seg, size, &h);
            if (count < size) { /* the piece reached first, the rest a part of its own */
                int64_t j = 0;
                for (int64_t i = 0; i < count; i++) tmp[j++] = g.queue[i];
                for (int64_t i = 0; i < size; i++)
                    if (g.level[seg[i]] < 0) tmp[j++] = seg[i];
                memcpy(seg, tmp, (size_t)size * sizeof *seg);
                stack[sp++] = lo + count;
                stack[sp++] = hi;
                size = count;
            }
            if (size <= ND_LEAF || h < 2) {
                for (int64_t i = 0; i < size; i++) seg[i] = g.queue[size - 1 - i];
                continue;
            }
            int64_t a, b;
            dissect(&g, s, seg, size, h, counts, tmp, &a, &b);
            stack[sp++] = lo;
            stack[sp++] = lo + a;
            stack[sp++] = lo + a;
            stack[sp++] = lo + a + b;
        }
    }
    free(g.stamp);
    free(g.level);
    free(g.queue);
    free(tmp);
    free(counts);
    free(stack);
    return ok ? 0 : -1;
}

/* ------------------------------------------------------------------------------------------------
 * symbolic factorisation */

typedef struct {
    int64_t n;
    const int64_t *indptr, *indices;
    const double *data;
    int64_t *perm, *iperm; /* pivot k is vertex perm[k]; iperm its inverse */
} pattern;

/* Elimination tree of the permuted matrix (parent[k], -1 for a root), with path-compressed ancestors. */
static void etree(const pattern *a, int64_t *parent, int64_t *ancestor) {
    for (int64_t k = 0; k < a->n; k++) {
        parent[k] = -1;
        ancestor[k] = -1;
        int64_t v = a->perm[k];
        for (int64_t p = a->indptr[v]; p < a->indptr[v + 1]; p++) {
            int64_t i = a->iperm[a->indices[p]], next;
            for (; i != -1 && i < k; i = next) {
                next = ancestor[i];
                ancestor[i] = k;
                if (next == -1) parent[i] = k;
            }
        }
    }
}

/* post[k] = the tree node visited k-th by a depth-first postorder (children in increasing order). */
static void postorder(int64_t n, const int64_t *parent, int64_t *post, int64_t *head, int64_t *next, int64_t *stack) {
    for (int64_t j = 0; j < n; j++) head[j] = -1;
    for (int64_t j = n - 1; j >= 0; j--) {
        if (parent[j] < 0) continue;
        next[j] = head[parent[j]];
        head[parent[j]] = j;
    }
    int64_t k = 0;
    for (int64_t r = 0; r < n; r++) {
        if (parent[r] >= 0) continue;
        int64_t top = 0;
        stack[top++] = r;
        while (top > 0) {
            int64_t p = stack[top - 1], c = head[p];
            if (c < 0) {
                post[k++] = p;
                top--;
            } else {
                head[p] = next[c];
                stack[top++] = c;
            }
        }
    }
}

/* counts[j] = nonzeros of column j of L (diagonal included): row k's pattern is the union of the tree
 * paths from each A(k, i), i < k, up to k, walked once each with a marker. */
static void column_counts(const pattern *a, const int64_t *parent, int64_t *counts, int64_t *mark) {
    for (int64_t j = 0; j < a->n; j++) {
        counts[j] = 1;
        mark[j] = -1;
    }
    for (int64_t k = 0; k < a->n; k++) {
        mark[k] = k;
        int64_t v = a->perm[k];
        for (int64_t p = a->indptr[v]; p < a->indptr[v + 1]; p++) {
            for (int64_t i = a->iperm[a->indices[p]]; i < k && mark[i] != k; i = parent[i]) {
                counts[i]++;
                mark[i] = k;
            }
        }
    }
}

typedef struct {
    int64_t n_super;
    int64_t *first;   /* (n_super + 1) */
    int64_t *sparent; /* parent supernode, -1 for a root */
    int64_t *size;    /* rows of each supernode's structure */
} supernodes;

/* Fundamental supernodes (column j + 1 continues j's when it is j's parent, j its only child, and its
 * structure is j's less j), then relaxed: a supernode whose only child ends right before it absorbs that
 * child when the merged panel stays nearly full (see RELAX_*). Writes sn->first/sparent/size; returns
 * the count. */
static int64_t find_supernodes(int64_t n, const int64_t *parent, const int64_t *cc, int64_t *nchild,
                               int64_t *snode, supernodes *sn) {
    for (int64_t j = 0; j < n; j++) nchild[j] = 0;
    for (int64_t j = 0; j < n; j++)
        if (parent[j] >= 0) nchild[parent[j]]++;
    int64_t ns = 0;
    for (int64_t j = 0; j < n; j++) {
        int fundamental = j > 0 && parent[j - 1] == j && cc[j - 1] == cc[j] + 1 && nchild[j] == 1;
        if (!fundamental) {
            sn->first[ns] = j;
            sn->size[ns] = cc[j];
            ns++;
        }
        snode[j] = ns - 1;
    }
    sn->first[ns] = n;
    /* relax: walk supernodes upwards; merge the group before J into J when it is J's only child and ends
     * right before it. nz: the group's true nonzeros (column counts), so the zeros a merge admits are
     * counted over the whole group, not per merge. */
    int64_t out = 0, nz = 0;
    for (int64_t J = 0; J < ns; J++) {
        int64_t f = sn->first[J], l = sn->first[J + 1], k = l - f, nz_j = 0;
        for (int64_t j = f; j < l; j++) nz_j += cc[j];
        if (out > 0 && parent[f - 1] == f && nchild[f] == 1) {
            int64_t pk = f - sn->first[out - 1], cols = pk + k;
            int64_t rows = pk + sn->size[J]; /* the group's pivots, then J's structure */
            int64_t stored = rows * cols - cols * (cols - 1) / 2;
            int small = pk <= RELAX_SMALL && k <= RELAX_SMALL;
            if (small || (double)(stored - nz - nz_j) <= RELAX_ZEROS * (double)stored) {
                sn->size[out - 1] = rows;
                nz += nz_j;
                continue; /* J joins the group */
            }
        }
        sn->first[out] = f;
        sn->size[out] = sn->size[J];
        nz = nz_j;
        out++;
    }
    sn->first[out] = n;
    for (int64_t J = 0; J < out; J++)
        for (int64_t j = sn->first[J]; j < sn->first[J + 1]; j++) snode[j] = J;
    for (int64_t J = 0; J < out; J++) {
        int64_t p = parent[sn->first[J + 1] - 1];
        sn->sparent[J] = p < 0 ? -1 : snode[p];
    }
    sn->n_super = out;
    return out;
}

static int cmp_i32(const void *x, const void *y) {
    int32_t a = *(const int32_t *)x, b = *(const int32_t *)y;
    return (a > b) - (a < b);
}

/* Each supernode's rows: its pivots, then (ascending) the rows of A's columns in it and of its
 * children's structures below its last pivot. head/next: the supernodes' children lists. */
static void supernode_rows(const pattern *a, const supernodes *sn, spd_factor *f, int64_t *marker, int64_t *head,
                           int64_t *next) {
    int64_t ns = sn->n_super;
    for (int64_t J = 0; J < ns; J++) head[J] = -1;
    for (int64_t J = ns - 1; J >= 0; J--) {
        if (sn->sparent[J] < 0) continue;
        next[J] = head[sn->sparent[J]];
        head[sn->sparent[J]] = J;
    }
    for (int64_t i = 0; i < a->n; i++) marker[i] = -1;
    for (int64_t J = 0; J < ns; J++) {
        int64_t fj = sn->first[J], l = sn->first[J + 1];
        int32_t *r = f->rows + f->rptr[J];
        int64_t cnt = 0;
        for (int64_t j = fj; j < l; j++) {
            r[cnt++] = (int32_t)j;
            marker[j] = J;
        }
        for (int64_t j = fj; j < l; j++) {
            int64_t v = a->perm[j];
            for (int64_t p = a->indptr[v]; p < a->indptr[v + 1]; p++) {
                int64_t i = a->iperm[a->indices[p]];
                if (i >= l && marker[i] != J) {
                    marker[i] = J;
                    r[cnt++] = (int32_t)i;
                }
            }
        }
        for (int64_t C = head[J]; C >= 0; C = next[C]) {
            const int32_t *rc = f->rows + f->rptr[C];
            int64_t kc = sn->first[C + 1] - sn->first[C], mc = f->rptr[C + 1] - f->rptr[C];
            for (int64_t q = kc; q < mc; q++)
                if (marker[rc[q]] != J) {
                    marker[rc[q]] = J;
                    r[cnt++] = rc[q];
                }
        }
        qsort(r + (l - fj), (size_t)(cnt - (l - fj)), sizeof *r, cmp_i32);
    }
}

/* ------------------------------------------------------------------------------------------------
 * numeric factorisation */

/* Factors the first k columns of the front F (m x m, lower triangle, column-major) in place, and leaves
 * in F[k:, k:] the update matrix F22 - L21 L21^T. Pivots are taken FRONT_BLOCK at a time: each block is
 * factored column by column, then applied to the rest in one pass. Returns -1, or the first pivot that
 * is not positive. */
static int64_t front_factor(double *F, int64_t m, int64_t k) {
    for (int64_t j0 = 0; j0 < k; j0 += FRONT_BLOCK) {
        int64_t j1 = j0 + FRONT_BLOCK < k ? j0 + FRONT_BLOCK : k;
        for (int64_t j = j0; j < j1; j++) { /* the block's own columns */
            double *cj = F + m * j;
            double d = cj[j];
            if (!(d > 0.0) || !isfinite(d)) return j;
            d = sqrt(d);
            cj[j] = d;
            for (int64_t i = j + 1; i < m; i++) cj[i] /= d;
            for (int64_t c = j + 1; c < j1; c++) {
                double s = cj[c], *cc = F + m * c;
                for (int64_t i = c; i < m; i++) cc[i] -= cj[i] * s;
            }
        }
        for (int64_t c = j1; c < m; c++) { /* the rest: column c -= sum over the block's columns */
            double *cc = F + m * c;
            int64_t j = j0;
            for (; j + 4 <= j1; j += 4) {
                const double *c0 = F + m * j, *c1 = c0 + m, *c2 = c1 + m, *c3 = c2 + m;
                double s0 = c0[c], s1 = c1[c], s2 = c2[c], s3 = c3[c];
                for (int64_t i = c; i < m; i++) cc[i] -= ((c0[i] * s0 + c1[i] * s1) + (c2[i] * s2 + c3[i] * s3));
            }
            for (; j < j1; j++) {
                const double *cj = F + m * j;
                double s = cj[c];
                for (int64_t i = c; i < m; i++) cc[i] -= cj[i] * s;
            }
        }
    }
    return -1;
}

typedef struct {
    double *buf;
    int64_t *off, *who; /* each entry's offset and supernode */
    int64_t depth, top;
} update_stack;

/* Multifrontal factorisation into f->val; returns -1, or the pivot (permuted) that is not positive. */
static int64_t numeric(const pattern *a, const supernodes *sn, spd_factor *f, double *front, update_stack *st,
                       int32_t *pos, const int64_t *nchild_s) {
    for (int64_t J = 0; J < sn->n_super; J++) {
        int64_t fj = sn->first[J], k = sn->first[J + 1] - fj;
        int64_t m = f->rptr[J + 1] - f->rptr[J];
        const int32_t *R = f->rows + f->rptr[J];
        for (int64_t i = 0; i < m; i++) pos[R[i]] = (int32_t)i;
        memset(front, 0, (size_t)(m * m) * sizeof *front);
        for (int64_t jj = 0; jj < k; jj++) {
            int64_t v = a->perm[fj + jj];
            double *col = front + m * jj;
            for (int64_t p = a->indptr[v]; p < a->indptr[v + 1]; p++) {
                int64_t i = a->iperm[a->indices[p]];
                if (i >= fj + jj) col[pos[i]] += a->data[p];
            }
        }
        int64_t base = st->depth - nchild_s[J];
        for (int64_t e = base; e < st->depth; e++) { /* extend-add the children's updates, oldest first */
            int64_t C = st->who[e], kc = sn->first[C + 1] - sn->first[C];
            int64_t mu = f->rptr[C + 1] - f->rptr[C] - kc;
            const int32_t *rc = f->rows + f->rptr[C] + kc;
            const double *U = st->buf + st->off[e];
            for (int64_t c = 0; c < mu; c++) {
                double *col = front + m * pos[rc[c]];
                const double *uc = U + mu * c;
                for (int64_t r = c; r < mu; r++) col[pos[rc[r]]] += uc[r];
            }
        }
        if (base < st->depth) st->top = st->off[base];
        st->depth = base;
        int64_t bad = front_factor(front, m, k);
        if (bad >= 0) return fj + bad;
        memcpy(f->val + f->vptr[J], front, (size_t)(m * k) * sizeof *front);
        int64_t mu = m - k;
        if (sn->sparent[J] >= 0 && mu > 0) {
            double *U = st->buf + st->top;
            for (int64_t c = 0; c < mu; c++)
                memcpy(U + mu * c + c, front + m * (k + c) + k + c, (size_t)(mu - c) * sizeof *U);
            st->off[st->depth] = st->top;
            st->who[st->depth++] = J;
            st->top += mu * mu;
        }
    }
    return -1;
}

/* ------------------------------------------------------------------------------------------------
 * the factor entry */

static void factor_free(spd_factor *f) {
    if (!f) return;
    free(f->perm);
    free(f->first);
    free(f->rptr);
    free(f->rows);
    free(f->vptr);
    free(f->val);
    free(f->work);
    free(f->block);
    free(f->rhs);
    free(f->elem);
    free(f);
}

/* The ordering into a->perm (perm_in for ORDER_GIVEN, checked to be a permutation). */
static int order_pattern(pattern *a, int32_t ordering, const int64_t *perm_in) {
    int64_t n = a->n;
    if (ordering == ORDER_GIVEN) {
        for (int64_t k = 0; k < n; k++) a->iperm[k] = -1;
        for (int64_t k = 0; k < n; k++) {
            int64_t v = perm_in[k];
            if (v < 0 || v >= n || a->iperm[v] >= 0) return ST_INPUT;
            a->iperm[v] = k;
            a->perm[k] = v;
        }
        return ST_OK;
    }
    if (ordering != ORDER_NESTED_DISSECTION) {
        for (int64_t k = 0; k < n; k++) a->perm[k] = k;
        return ST_OK;
    }
    int64_t *xadj = alloc(n + 1, sizeof(int64_t));
    int32_t *adj = alloc(a->indptr[n], sizeof(int32_t));
    int status = xadj && adj ? ST_OK : ST_MEMORY;
    if (status == ST_OK) {
        xadj[0] = 0;
        for (int64_t v = 0; v < n; v++) {
            int64_t d = xadj[v];
            for (int64_t p = a->indptr[v]; p < a->indptr[v + 1]; p++)
                if (a->indices[p] != v) adj[d++] = (int32_t)a->indices[p];
            xadj[v + 1] = d;
        }
        if (nested_dissection(n, xadj, adj, a->perm) < 0) status = ST_MEMORY;
    }
    free(xadj);
    free(adj);
    return status;
}

/* Postorders the elimination tree: perm and parent renumbered, iperm set. */
static int postordered(pattern *a, int64_t *parent, int64_t *t1, int64_t *t2, int64_t *t3) {
    int64_t n = a->n;
    int64_t *post = alloc(n, sizeof(int64_t)), *old = alloc(n, sizeof(int64_t));
    if (!post || !old) {
        free(post);
        free(old);
        return ST_MEMORY;
    }
    postorder(n, parent, post, t1, t2, t3);
    for (int64_t k = 0; k < n; k++) t1[post[k]] = k; /* t1: inverse of post */
    for (int64_t k = 0; k < n; k++) old[k] = a->perm[k];
    for (int64_t k = 0; k < n; k++) {
        a->perm[k] = old[post[k]];
        t2[k] = parent[post[k]] < 0 ? -1 : t1[parent[post[k]]];
    }
    memcpy(parent, t2, (size_t)n * sizeof *parent);
    for (int64_t k = 0; k < n; k++) a->iperm[a->perm[k]] = k;
    free(post);
    free(old);
    return ST_OK;
}

/* Symbolic and numeric factorisation of the ordered pattern into f; info filled. */
static int factor_ordered(pattern *a, spd_factor *f, int64_t *info) {
    int64_t n = a->n;
    int64_t *parent = alloc(n, sizeof(int64_t)), *t1 = alloc(n + 1, sizeof(int64_t));
    int64_t *t2 = alloc(n + 1, sizeof(int64_t)), *t3 = alloc(n + 1, sizeof(int64_t));
    int64_t *cc = alloc(n, sizeof(int64_t));
    supernodes sn = {0, alloc(n + 1, sizeof(int64_t)), alloc(n, sizeof(int64_t)), alloc(n + 1, sizeof(int64_t))};
    update_stack st = {NULL, alloc(n + 1, sizeof(int64_t)), alloc(n + 1, sizeof(int64_t)), 0, 0};
    int32_t *pos = alloc(n, sizeof(int32_t));
    double *front = NULL;
    int status = ST_MEMORY;
    if (!parent || !t1 || !t2 || !t3 || !cc || !sn.first || !sn.sparent || !sn.size || !st.off || !st.who || !pos)
        goto done;
    for (int64_t k = 0; k < n; k++) a->iperm[a->perm[k]] = k;
    etree(a, parent, t1);
    if (postordered(a, parent, t1, t2, t3) != ST_OK) goto done;
    column_counts(a, parent, cc, t1);
    int64_t nnz_l = 0;
    for (int64_t j = 0; j < n; j++) nnz_l += cc[j];
    int64_t ns = find_supernodes(n, parent, cc, t1, t2, &sn);
    f->first = alloc(ns + 1, sizeof(int64_t));
    f->rptr = alloc(ns + 1, sizeof(int64_t));
    f->vptr = alloc(ns + 1, sizeof(int64_t));
    if (!f->first || !f->rptr || !f->vptr) goto done;
    int64_t max_front = 0, flops = 0, top = 0, max_top = 0;
    f->rptr[0] = f->vptr[0] = 0;
    for (int64_t J = 0; J < ns; J++) {
        int64_t k = sn.first[J + 1] - sn.first[J], m = sn.size[J];
        f->first[J] = sn.first[J];
        f->rptr[J + 1] = f->rptr[J] + m;
        f->vptr[J + 1] = f->vptr[J] + m * k;
        if (m > max_front) max_front = m;
        for (int64_t j = 0; j < k; j++) flops += (m - j) * (m - j);
        t3[J] = 0;
    }
    f->first[ns] = n;
    /* t3: each supernode's children on the update stack (every non-root: its structure reaches below it) */
    for (int64_t J = 0; J < ns; J++)
        if (sn.sparent[J] >= 0 && sn.size[J] > sn.first[J + 1] - sn.first[J]) t3[sn.sparent[J]]++;
    /* the update stack's high-water mark, by replaying the pushes and pops */
    int64_t *depth_size = t2, depth = 0;
    for (int64_t J = 0; J < ns; J++) {
        for (int64_t c = 0; c < t3[J]; c++) top -= depth_size[--depth];
        int64_t mu = sn.size[J] - (sn.first[J + 1] - sn.first[J]);
        if (sn.sparent[J] >= 0 && mu > 0) {
            depth_size[depth++] = mu * mu;
            top += mu * mu;
            if (top > max_top) max_top = top;
        }
    }
    f->rows = alloc(f->rptr[ns], sizeof(int32_t));
    f->val = alloc(f->vptr[ns], sizeof(double));
    front = alloc(max_front * max_front, sizeof(double));
    st.buf = alloc(max_top, sizeof(double));
    if (!f->rows || !f->val || !front || !st.buf) goto done;
    supernode_rows(a, &sn, f, cc, t1, t2);
    int64_t bad = numeric(a, &sn, f, front, &st, pos, t3);
    f->n_super = ns;
    info[I_NNZ_L] = nnz_l;
    info[I_SUPERNODES] = ns;
    info[I_STORED] = f->vptr[ns];
    info[I_FLOPS] = flops;
    info[I_MAX_FRONT] = max_front;
    if (bad >= 0) {
        info[I_PIVOT] = a->perm[bad];
        status = ST_NOT_SPD;
        goto done;
    }
    status = ST_OK;
done:
    free(parent);
    free(t1);
    free(t2);
    free(t3);
    free(cc);
    free(sn.first);
    free(sn.sparent);
    free(sn.size);
    free(st.buf);
    free(st.off);
    free(st.who);
    free(pos);
    free(front);
    return status;
}

int64_t ak_spd_factor(int64_t n, const int64_t *indptr, const int64_t *indices, const double *data,
                      int32_t ordering, const int64_t *perm_in, int64_t *perm_out, int64_t *info, void **handle) {
    for (int i = 0; i < I_SLOTS; i++) info[i] = 0;
    info[I_PIVOT] = -1;
    *handle = NULL;
    spd_factor *f = calloc(1, sizeof *f);
    pattern a = {n, indptr, indices, data, NULL, alloc(n, sizeof(int64_t))};
    int status = ST_MEMORY;
    if (f && a.iperm) {
        f->n = n;
        f->perm = a.perm = alloc(n, sizeof(int64_t));
        f->work = alloc(3 * n, sizeof(double));
        f->rhs = alloc(3 * n, sizeof(double));
        if (f->perm && f->work && f->rhs) status = order_pattern(&a, ordering, perm_in);
        if (status == ST_OK) status = factor_ordered(&a, f, info);
        if (status == ST_OK) {
            f->block = alloc(3 * info[I_MAX_FRONT], sizeof(double));
            if (!f->block) status = ST_MEMORY;
        }
    }
    free(a.iperm);
    info[I_STATUS] = status;
    if (status != ST_OK) {
        factor_free(f);
        return status;
    }
    memcpy(perm_out, f->perm, (size_t)n * sizeof *perm_out);
    f->bytes = (int64_t)sizeof *f + (n * (int64_t)(sizeof(int64_t) + 6 * sizeof(double))) +
               3 * info[I_MAX_FRONT] * (int64_t)sizeof(double) +
               3 * (f->n_super + 1) * (int64_t)sizeof(int64_t) + f->rptr[f->n_super] * (int64_t)sizeof(int32_t) +
               f->vptr[f->n_super] * (int64_t)sizeof(double);
    info[I_BYTES] = f->bytes;
    *handle = f;
    return ST_OK;
}

int64_t ak_spd_free(void *handle) {
    factor_free(handle);
    return 0;
}

/* ------------------------------------------------------------------------------------------------
 * solve */

/* L L^T w = w for permuted right-hand sides w (n, 3) row-major. Each supernode gathers its rows of w into
 * x (3 planes of its m rows: dense, contiguous loops), substitutes through its panel and scatters back:
 * forward, x[j] /= L[j][j] then x[i] -= L[i][j] x[j] below; backward, x[j] = (x[j] - sum_i L[i][j] x[i])
 * / L[j][j], the sum in four interleaved partial sums added in a fixed order. */
/* x[r * m + i] = w[R[i]][r]: a supernode's rows of the right-hand sides, as three planes. */
static inline void gather_block(const double *w, const int32_t *R, int64_t m, double *x) {
    for (int64_t i = 0; i < m; i++) {
        const double *wi = w + 3 * (int64_t)R[i];
        x[i] = wi[0];
        x[m + i] = wi[1];
        x[2 * m + i] = wi[2];
    }
}

static void solve_permuted(const spd_factor *f, double *w, double *x) {
    for (int64_t J = 0; J < f->n_super; J++) {
        int64_t fj = f->first[J], nc = f->first[J + 1] - fj, m = f->rptr[J + 1] - f->rptr[J];
        const int32_t *R = f->rows + f->rptr[J];
        const double *L = f->val + f->vptr[J];
        double *x0 = x, *x1 = x + m, *x2 = x + 2 * m;
        gather_block(w, R, m, x);
        for (int64_t j = 0; j < nc; j++) {
            const double *col = L + m * j;
            double d = col[j], a0 = x0[j] / d, a1 = x1[j] / d, a2 = x2[j] / d;
            x0[j] = a0;
            x1[j] = a1;
            x2[j] = a2;
            for (int64_t i = j + 1; i < m; i++) {
                double li = col[i];
                x0[i] -= li * a0;
                x1[i] -= li * a1;
                x2[i] -= li * a2;
            }
        }
        for (int64_t i = 0; i < m; i++) {
            double *wi = w + 3 * (int64_t)R[i];
            wi[0] = x0[i];
            wi[1] = x1[i];
            wi[2] = x2[i];
        }
    }
    for (int64_t J = f->n_super - 1; J >= 0; J--) {
        int64_t nc = f->first[J + 1] - f->first[J], m = f->rptr[J + 1] - f->rptr[J];
        const int32_t *R = f->rows + f->rptr[J];
        const double *L = f->val + f->vptr[J];
        double *x0 = x, *x1 = x + m, *x2 = x + 2 * m;
        gather_block(w, R, m, x);
        for (int64_t j = nc - 1; j >= 0; j--) {
            const double *col = L + m * j;
            double s0[4] = {0, 0, 0, 0}, s1[4] = {0, 0, 0, 0}, s2[4] = {0, 0, 0, 0};
            int64_t i = j + 1;
            for (; i + 4 <= m; i += 4)
                for (int q = 0; q < 4; q++) {
                    s0[q] += col[i + q] * x0[i + q];
                    s1[q] += col[i + q] * x1[i + q];
                    s2[q] += col[i + q] * x2[i + q];
                }
            for (int q = 0; i < m; i++, q++) {
                s0[q] += col[i] * x0[i];
                s1[q] += col[i] * x1[i];
                s2[q] += col[i] * x2[i];
            }
            x0[j] = (x0[j] - ((s0[0] + s0[1]) + (s0[2] + s0[3]))) / col[j];
            x1[j] = (x1[j] - ((s1[0] + s1[1]) + (s1[2] + s1[3]))) / col[j];
            x2[j] = (x2[j] - ((s2[0] + s2[1]) + (s2[2] + s2[3]))) / col[j];
        }
        for (int64_t i = 0; i < nc; i++) {
            double *wi = w + 3 * (int64_t)R[i];
            wi[0] = x0[i];
            wi[1] = x1[i];
            wi[2] = x2[i];
        }
    }
}

/* b (n, 3) row-major := A^-1 b. */
static void solve_into(const spd_factor *f, double *b) {
    double *w = f->work;
    for (int64_t i = 0; i < f->n; i++) memcpy(w + 3 * i, b + 3 * f->perm[i], 3 * sizeof *w);
    solve_permuted(f, w, f->block);
    for (int64_t i = 0; i < f->n; i++) memcpy(b + 3 * f->perm[i], w + 3 * i, 3 * sizeof *w);
}

/* b (n, k) row-major := A^-1 b, three columns at a time. */
int64_t ak_spd_solve(void *handle, double *b, int64_t k) {
    spd_factor *f = handle;
    if (!f || k < 1) return -3;
    if (k == 3) {
        solve_into(f, b);
        return 0;
    }
    double *c = alloc(3 * f->n, sizeof(double));
    if (!c) return -1;
    for (int64_t r0 = 0; r0 < k; r0 += 3) {
        int64_t nr = k - r0 < 3 ? k - r0 : 3;
        for (int64_t i = 0; i < f->n; i++)
            for (int64_t r = 0; r < 3; r++) c[3 * i + r] = r < nr ? b[i * k + r0 + r] : 0.0;
        solve_into(f, c);
        for (int64_t i = 0; i < f->n; i++)
            for (int64_t r = 0; r < nr; r++) b[i * k + r0 + r] = c[3 * i + r];
    }
    free(c);
    return 0;
}

/* ------------------------------------------------------------------------------------------------
 * the pass's frame */

typedef struct {
    int64_t n, n_elem, k;
    const int64_t *corners;
    const double *grads, *weights, *normals, *motions, *field;
} arap_elements;

static inline int64_t corner(const arap_elements *e, int64_t t, int64_t c) {
    int64_t v = e->corners[t * e->k + c];
    return v < 0 ? 0 : (v >= e->n ? e->n - 1 : v); /* clamped: wrong indices never read out of bounds */
}

/* The blended map of element t (row-major 3x3) from the planar columns motions[c, t, :]. */
static void element_map(const arap_elements *e, int64_t t, double A[9]) {
    for (int c = 0; c < 3; c++)
        for (int r = 0; r < 3; r++) A[3 * r + c] = e->motions[(c * e->n_elem + t) * 3 + r];
}

/* F = sum_c x[corner c] g_c^T (row-major). */
static void gradient_of(const arap_elements *e, int64_t t, const double *x, double F[9]) {
    for (int i = 0; i < 9; i++) F[i] = 0.0;
    for (int64_t c = 0; c < e->k; c++) {
        const double *p = x + 3 * corner(e, t, c), *g = e->grads + (t * e->k + c) * 3;
        for (int r = 0; r < 3; r++)
            for (int s = 0; s < 3; s++) F[3 * r + s] += p[r] * g[s];
    }
}

/* rhs = sum_t w_t (T_t - F_t(field)) g_c at each corner c; T_t from targets (9 per element, row-major,
 * stride 18) or, when targets is NULL, the blended maps. */
static void right_hand_side(const arap_elements *e, const double *targets, double *rhs) {
    memset(rhs, 0, (size_t)(3 * e->n) * sizeof *rhs);
    for (int64_t t = 0; t < e->n_elem; t++) {
        double T[9], F[9], M[9];
        if (targets)
            memcpy(T, targets + 18 * t + 9, sizeof T);
        else
            element_map(e, t, T);
        gradient_of(e, t, e->field, F);
        double w = e->weights[t];
        for (int i = 0; i < 9; i++) M[i] = w * (T[i] - F[i]);
        for (int64_t c = 0; c < e->k; c++) {
            double *b = rhs + 3 * corner(e, t, c);
            const double *g = e->grads + (t * e->k + c) * 3;
            for (int r = 0; r < 3; r++) b[r] += (M[3 * r] * g[0] + M[3 * r + 1] * g[1]) + M[3 * r + 2] * g[2];
        }
    }
}

static void matmul3(const double A[9], const double B[9], double C[9]) {
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) C[3 * r + c] = (A[3 * r] * B[c] + A[3 * r + 1] * B[3 + c]) + A[3 * r + 2] * B[6 + c];
}

/* The polar factors of n <= POLAR_BLOCK matrices at once, in place: q[i * POLAR_BLOCK + j] is entry i
 * (row-major) of matrix j. Newton's iteration Q <- (zeta Q + Q^-T / zeta)/2 from Q = X, with Higham's
 * scaling zeta = (|Q^-1|_F / |Q|_F)^(1/2) and Q^-T = cof(Q)/det Q, until a step changes Q by at most
 * NEWTON_TOL |Q|_F (quadratic convergence: a handful of steps). For det X > 0 the limit is the rotation
 * nearest X. Each column keeps the step that converged it (later passes select its old value), so its
 * result does not depend on the other columns; the loop has no branches and vectorises. ok[j] = 1 where
 * column j converged, 0 where det Q was not positive or finite or NEWTON_STEPS did not suffice (the
 * caller then takes the SVD). */
static void polar_block(double *restrict q, int64_t n, int8_t *restrict ok) {
    int8_t done[POLAR_BLOCK], bad[POLAR_BLOCK];
    for (int64_t j = 0; j < n; j++) done[j] = bad[j] = 0;
    for (int step = 0; step < NEWTON_STEPS; step++) {
        int open = 0;
        for (int64_t j = 0; j < n; j++) {
            double Q[9], C[9];
            for (int i = 0; i < 9; i++) Q[i] = q[i * POLAR_BLOCK + j];
            C[0] = Q[4] * Q[8] - Q[5] * Q[7];
            C[1] = Q[5] * Q[6] - Q[3] * Q[8];
            C[2] = Q[3] * Q[7] - Q[4] * Q[6];
            C[3] = Q[2] * Q[7] - Q[1] * Q[8];
            C[4] = Q[0] * Q[8] - Q[2] * Q[6];
            C[5] = Q[1] * Q[6] - Q[0] * Q[7];
            C[6] = Q[1] * Q[5] - Q[2] * Q[4];
            C[7] = Q[2] * Q[3] - Q[0] * Q[5];
            C[8] = Q[0] * Q[4] - Q[1] * Q[3];
            double det = (Q[0] * C[0] + Q[1] * C[1]) + Q[2] * C[2];
            double nq = 0.0, nc = 0.0;
            for (int i = 0; i < 9; i++) {
                nq += Q[i] * Q[i];
                nc += C[i] * C[i];
            }
            int usable = det > 0.0 && det < INFINITY && nq > 0.0 && nq < INFINITY && nc < INFINITY;
            int frozen = done[j] | bad[j];
            double safe_det = usable ? det : 1.0, safe_nq = usable ? nq : 1.0, safe_nc = usable ? nc : 1.0;
            double zeta = sqrt(sqrt(safe_nc / safe_nq) / safe_det), a = 0.5 * zeta, b = 0.5 / (zeta * safe_det);
            double change = 0.0, norm = 0.0;
            for (int i = 0; i < 9; i++) {
                double v = a * Q[i] + b * C[i];
                change += (v - Q[i]) * (v - Q[i]);
                norm += v * v;
                q[i * POLAR_BLOCK + j] = frozen ? Q[i] : v;
            }
            int now = change <= NEWTON_TOL * NEWTON_TOL * norm;
            bad[j] = (int8_t)(bad[j] | ((!frozen) & (!usable)));
            done[j] = (int8_t)(done[j] | ((!frozen) & usable & now));
            open |= !(done[j] | bad[j]);
        }
        if (!open) break;
    }
    for (int64_t j = 0; j < n; j++) ok[j] = (int8_t)(done[j] & !bad[j]);
}

/* R = U V^T for the SVD of X, the direction of the least singular value taken as the cross product of
 * the other two (det R = 1 even when det X <= 0): the rotation nearest X. Returns 0 (R untouched) when X
 * has rank < 2. */
static int rotation_svd(const double X[9], double R[9]) {
    double A[9], V[9], s[3], U[9];
    memcpy(A, X, sizeof A);
    ak_jacobi3(A, V);
    for (int c = 0; c < 3; c++) s[c] = sqrt(A[c] * A[c] + A[3 + c] * A[3 + c] + A[6 + c] * A[6 + c]);
    int lo = s[0] <= s[1] ? (s[0] <= s[2] ? 0 : 2) : (s[1] <= s[2] ? 1 : 2);
    int a = (lo + 1) % 3, b = (lo + 2) % 3;
    if (!(s[a] > 0.0 && s[b] > 0.0) || !isfinite(s[a] + s[b])) return 0;
    for (int r = 0; r < 3; r++) {
        U[3 * r + a] = A[3 * r + a] / s[a];
        U[3 * r + b] = A[3 * r + b] / s[b];
    }
    U[lo] = U[3 + a] * U[6 + b] - U[6 + a] * U[3 + b];
    U[3 + lo] = U[6 + a] * U[b] - U[a] * U[6 + b];
    U[6 + lo] = U[a] * U[3 + b] - U[3 + a] * U[b];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++)
            R[3 * r + c] = (U[3 * r] * V[3 * c] + U[3 * r + 1] * V[3 * c + 1]) + U[3 * r + 2] * V[3 * c + 2];
    return 1;
}

/* S = (R^T A + A^T R)/2, the stretch of A's polar split from its polar factor R. */
static void stretch_from(const double R[9], const double A[9], double S[9]) {
    for (int r = 0; r < 3; r++)
        for (int c = r; c < 3; c++) {
            double rc = (R[r] * A[c] + R[3 + r] * A[3 + c]) + R[6 + r] * A[6 + c];
            double cr = (R[c] * A[r] + R[3 + c] * A[3 + r]) + R[6 + c] * A[6 + r];
            S[3 * r + c] = S[3 * c + r] = 0.5 * (rc + cr);
        }
}

/* The completed solved gradient times the stretch, X = (F(x) + T n n^T) S, of element t; buf holds
 * (S, T) per element. */
static void completed_times_stretch(const arap_elements *e, int64_t t, const double *x, const double *buf,
                                    double X[9]) {
    const double *S = buf + 18 * t, *T = S + 9, *nv = e->normals + 3 * t;
    double F[9];
    gradient_of(e, t, x, F);
    for (int r = 0; r < 3; r++) {
        double tn = (T[3 * r] * nv[0] + T[3 * r + 1] * nv[1]) + T[3 * r + 2] * nv[2];
        for (int c = 0; c < 3; c++) F[3 * r + c] += tn * nv[c];
    }
    matmul3(F, S, X);
}

/* The first extra iteration's set-up: per element S (the blended map's stretch) and T = the blended map,
 * into buf (18 per element). */
static void stretches(const arap_elements *e, double *buf) {
    double q[9 * POLAR_BLOCK];
    int8_t ok[POLAR_BLOCK];
    for (int64_t t0 = 0; t0 < e->n_elem; t0 += POLAR_BLOCK) {
        int64_t nb = e->n_elem - t0 < POLAR_BLOCK ? e->n_elem - t0 : POLAR_BLOCK;
        for (int64_t j = 0; j < nb; j++) {
            double *T = buf + 18 * (t0 + j) + 9;
            element_map(e, t0 + j, T);
            for (int i = 0; i < 9; i++) q[i * POLAR_BLOCK + j] = T[i];
        }
        polar_block(q, nb, ok);
        for (int64_t j = 0; j < nb; j++) {
            double *S = buf + 18 * (t0 + j), *T = S + 9, R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
            if (ok[j])
                for (int i = 0; i < 9; i++) R[i] = q[i * POLAR_BLOCK + j];
            else
                rotation_svd(T, R); /* a blended map has det > 0: only rounding brings this here */
            stretch_from(R, T, S);
        }
    }
}

/* Targets of the next iteration: T = R S, R the rotation nearest (F(x) + T n n^T) S, in blocks. */
static void swap_rotations(const arap_elements *e, const double *x, double *buf) {
    double q[9 * POLAR_BLOCK];
    int8_t ok[POLAR_BLOCK];
    for (int64_t t0 = 0; t0 < e->n_elem; t0 += POLAR_BLOCK) {
        int64_t nb = e->n_elem - t0 < POLAR_BLOCK ? e->n_elem - t0 : POLAR_BLOCK;
        for (int64_t j = 0; j < nb; j++) {
            double X[9];
            completed_times_stretch(e, t0 + j, x, buf, X);
            for (int i = 0; i < 9; i++) q[i * POLAR_BLOCK + j] = X[i];
        }
        polar_block(q, nb, ok);
        for (int64_t j = 0; j < nb; j++) {
            double *S = buf + 18 * (t0 + j), *T = S + 9, R[9], X[9];
            int found = 1;
            if (ok[j]) {
                for (int i = 0; i < 9; i++) R[i] = q[i * POLAR_BLOCK + j];
            } else { /* det <= 0 (an element turned inside out): the SVD */
                completed_times_stretch(e, t0 + j, x, buf, X);
                found = rotation_svd(X, R);
            }
            if (found) matmul3(R, S, T);
        }
    }
}

int64_t ak_arap_frame(void *handle, int64_t n, int64_t n_elem, int64_t k, const int64_t *corners,
                      const double *grads, const double *weights, const double *normals, const double *motions,
                      const double *field, int64_t iterations, double *out) {
    spd_factor *f = handle;
    if (!f || n != f->n || n < 1 || (k != 3 && k != 4) || n_elem < 0 || iterations < 0) return -3;
    arap_elements e = {n, n_elem, k, corners, grads, weights, normals, motions, field};
    right_hand_side(&e, NULL, f->rhs);
    if (iterations == 0) {
        memcpy(out, f->rhs, (size_t)(3 * n) * sizeof *out);
        return 0;
    }
    if (iterations > 1 && f->elem_cap < n_elem) {
        free(f->elem);
        f->elem = alloc(18 * n_elem, sizeof(double));
        f->elem_cap = f->elem ? n_elem : 0;
        if (!f->elem) return -1;
        f->bytes += 18 * n_elem * (int64_t)sizeof(double);
    }
    for (int64_t it = 0; it < iterations; it++) {
        if (it == 1) stretches(&e, f->elem);
        if (it > 0) {
            swap_rotations(&e, out, f->elem);
            right_hand_side(&e, f->elem, f->rhs);
        }
        solve_into(f, f->rhs);
        for (int64_t i = 0; i < 3 * n; i++) out[i] = field[i] + f->rhs[i];
    }
    return 0;
}

int64_t ak_spd_bytes(void *handle) { return handle ? ((spd_factor *)handle)->bytes : 0; }
