/* jaxci._ckernels: the closed-form hexahedron kernels of the numpy (host) path as single fused C loops.
 *
 * The numpy path (jaxci.optim.host) evaluates F (Eq. 3.1) with its gradient, and the untangling stage's energy
 * with its gradient, a few hundred times per run. Written with numpy they are ~100 array operations over every
 * corner (20-30 ms at 27,000 hexahedra on the 2-core CPU, memory-bound); one loop over the elements that keeps
 * a corner's quantities in registers does the same arithmetic in a few ms. Same formulas as
 * jaxci.metrics.hexahedron._terms_and_grad and jaxci.optim._untangle_loop.hex_kernel (tested against them in float64).
 *
 * Arguments are Python buffers (numpy arrays: C-contiguous float64 / int64), checked here; no numpy C API, so
 * the build needs only the Python headers. Built by setup.py as an optional extension: without a C compiler
 * the install still succeeds and jaxci.native falls back to numpy.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <limits.h>
#include <math.h>
#include <pthread.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* CORNER_NEIGHBOURS of jaxci.mesh: the far ends of columns a, b, c of corner i (checked by a test). */
static const int NB[8][3] = {{1, 3, 4}, {2, 0, 5}, {3, 1, 6}, {0, 2, 7},
                             {7, 5, 0}, {4, 6, 1}, {5, 7, 2}, {6, 4, 3}};

static int get_buffer(PyObject *obj, Py_buffer *view, const char *name, const char *fmt, Py_ssize_t itemsize,
                      int writable) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0)
        return -1;
    if (view->itemsize != itemsize || view->format == NULL || strchr(fmt, view->format[0]) == NULL ||
        view->format[1] != '\0') {
        PyErr_Format(PyExc_TypeError, "%s: expected a contiguous array of %s, got format '%s'", name,
                     fmt[0] == '?' ? "bool" : fmt[0] == 'd' ? "float64" : fmt[0] == 'e' ? "float16" :
                     fmt[0] == 'i' ? "int32" : "int64",
                     view->format ? view->format : "?");
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* The array arguments of one call, acquired one after the other and released together (`release`); an absent
 * optional one (None) stays empty. */
typedef struct {
    Py_buffer view;
    int held;
} Buf;

static int acquire(Buf *b, PyObject *obj, const char *name, const char *fmt, int writable, int optional) {
    if (obj == Py_None && optional) return 0;
    Py_ssize_t itemsize = fmt[0] == '?' ? 1 : fmt[0] == 'e' ? 2 : (fmt[0] == 'i' || fmt[0] == 'f' ? 4 : 8);
    if (get_buffer(obj, &b->view, name, fmt, itemsize, writable) < 0) return -1;
    b->held = 1;
    return 0;
}

/* One array argument of an entry point: its name in messages, its formats (as acquire's fmt), whether the kernel
 * writes it and whether None may stand for it. */
typedef struct {
    const char *name, *fmt;
    int writable, optional;
} Arg;

/* acquire o[i] into B[i] as spec[i] says, for i < n, one after the other (-1 at the first that fails). */
static int acquire_args(Buf *B, PyObject *const *o, const Arg *spec, int n) {
    for (int i = 0; i < n; i++)
        if (acquire(&B[i], o[i], spec[i].name, spec[i].fmt, spec[i].writable, spec[i].optional) < 0) return -1;
    return 0;
}

static void release(Buf *b, int n) {
    for (int i = 0; i < n; i++)
        if (b[i].held) PyBuffer_Release(&b[i].view);
}

/* 0 if every one of the `count` indices I (int64, or int32 where `width` is 4) is in [0, n), else -1 with
 * IndexError naming the function. */
static int check_indices_of(const void *I, int width, Py_ssize_t count, Py_ssize_t n, const char *fn) {
    for (Py_ssize_t k = 0; k < count; k++) {
        long long i = width == 4 ? ((const int *)I)[k] : ((const long long *)I)[k];
        if (i < 0 || i >= n) {
            PyErr_Format(PyExc_IndexError, "%s: node index %lld out of range [0, %zd)", fn, i, n);
            return -1;
        }
    }
    return 0;
}

static int check_indices(const long long *I, Py_ssize_t count, Py_ssize_t n, const char *fn) {
    return check_indices_of(I, 8, count, n, fn);
}

/* The node numbers of a connectivity (hexahedra, cells) as every kernel takes them: int32, as jaxci.mesh keeps
 * them (half the bytes of int64: 6.6 MB at 216,000 hexahedra; a mesh has fewer than 2^31 nodes). */
typedef int32_t conn_t;

static int check_conn(const conn_t *I, Py_ssize_t count, Py_ssize_t n, const char *fn) {
    return check_indices_of(I, 4, count, n, fn);
}

/* What the condition workers add up: sum of (term - 1), max term, inverted corners (first in their jobs). */
typedef struct {
    double sum, tmax;
    long long invalid;
} Sums;

/* out += s: the sums and counts added, the larger max kept. */
static void add_sum(Sums *out, const Sums *s) {
    out->sum += s->sum;
    if (s->tmax > out->tmax) out->tmax = s->tmax;
    out->invalid += s->invalid;
}

/* The jobs' Sums (each `size` bytes, its Sums first) added up. */
static Sums add_sums(const void *jobs, size_t size, int nt) {
    Sums out = {0.0, 0.0, 0};
    for (int t = 0; t < nt; t++) add_sum(&out, (const Sums *)((const char *)jobs + t * size));
    return out;
}

/* add_sums as the tuple (sum, max, inverted). */
static PyObject *total_sums(const void *jobs, size_t size, int nt) {
    Sums out = add_sums(jobs, size, nt);
    return Py_BuildValue("ddL", out.sum, out.tmax, out.invalid);
}

static inline void cross(const double *x, const double *y, double *out) {
    out[0] = x[1] * y[2] - x[2] * y[1];
    out[1] = x[2] * y[0] - x[0] * y[2];
    out[2] = x[0] * y[1] - x[1] * y[0];
}

/* One corner with columns a, b, c: its term (kappa/3)^2 = |A|^2 |adj A|^2 / (9 det^2) in *term, and with
 * w2 != 0, w2 (9/2) d term / d(a, b, c) in ga, gb, gc (jaxci.metrics.hexahedron._terms_and_grad's p, q, r). Returns 0
 * (nothing written but *term = inf) where det <= 0. */
static inline int corner_term(const double *a, const double *b, const double *c, double w2, double *term,
                              double *ga, double *gb, double *gc) {
    double u[3], v[3], w[3];
    cross(b, c, u); cross(c, a, v); cross(a, b, w);
    double det = a[0] * u[0] + a[1] * u[1] + a[2] * u[2];
    if (!(det > 0.0)) {
        *term = INFINITY;
        return 0;
    }
    double fro2 = 0.0, adj2 = 0.0;
    for (int d = 0; d < 3; d++) {
        fro2 += a[d] * a[d] + b[d] * b[d] + c[d] * c[d];
        adj2 += u[d] * u[d] + v[d] * v[d] + w[d] * w[d];
    }
    double idet = 1.0 / det, idet2 = idet * idet;
    *term = fro2 * adj2 * idet2 * (1.0 / 9.0);
    if (w2 == 0.0) return 1;
    double p = w2 * adj2 * idet2, q = w2 * fro2 * idet2, r = p * fro2 * idet;
    double vxc[3], bxw[3], cxu[3], wxa[3], uxb[3], axv[3];
    cross(v, c, vxc); cross(b, w, bxw); cross(c, u, cxu); cross(w, a, wxa); cross(u, b, uxb); cross(a, v, axv);
    for (int d = 0; d < 3; d++) {
        ga[d] = p * a[d] + q * (vxc[d] + bxw[d]) - r * u[d];
        gb[d] = p * b[d] + q * (cxu[d] + wxa[d]) - r * v[d];
        gc[d] = p * c[d] + q * (uxb[d] + axv[d]) - r * w[d];
    }
    return 1;
}

/* Up to MAX_THREADS threads per call (kept between calls: _pool.c), each over its own range of elements with its
 * own gradient buffer (summed into the caller's at the end: no two threads write one node). A call over fewer
 * than MIN_PER_THREAD elements per thread uses fewer threads. With the threads kept, a call's second thread
 * costs ~15-25 us (2026-12-01, 2-core AMD EPYC VM, the polish's penalty pass over the first N hexahedra of a
 * tet-to-hex sphere, medians of 300 calls, two threads against one): N = 512 68 against 75 us, 1,024 118
 * against 158, 2,048 177 against 298, 4,096 406 against 602; hence 512. (Made for each call, a thread cost
 * ~300 us there: 4,096 hexahedra 624 us on two threads against 615 on one, and the bound was 2048.) */
#define MAX_THREADS 16
#define MIN_PER_THREAD 512

/* Threads for a call over n items: nthreads within [1, MAX_THREADS], fewer where a thread would get fewer than
 * min_per items (MIN_PER_THREAD elements for the element kernels; the node kernels set their own). */
static int threads_for(Py_ssize_t n, int nthreads, Py_ssize_t min_per) {
    int nt = nthreads < 1 ? 1 : (nthreads > MAX_THREADS ? MAX_THREADS : nthreads);
    while (nt > 1 && n / nt < min_per) nt--;
    return nt;
}

/* The nodes of the items (elements, corners) of a call: item i's k-th node is I[i * istride + k * kstride],
 * k < width; `items` of them, split among the threads as the jobs are (items * t / nt). */
typedef struct {
    const void *I; /* conn_t, or long long where `wide` */
    Py_ssize_t items, istride, kstride;
    int width, wide;
} Nodes;

/* [*lo, *hi): the range of the node numbers of items [a, b) of `nd` (empty: 0, 0). */
static void node_span(const Nodes *nd, Py_ssize_t a, Py_ssize_t b, Py_ssize_t *lo, Py_ssize_t *hi) {
    long long mn = LLONG_MAX, mx = -1;
    for (Py_ssize_t i = a; i < b; i++)
        for (int k = 0; k < nd->width; k++) {
            Py_ssize_t at = i * nd->istride + k * nd->kstride;
            long long v = nd->wide ? ((const long long *)nd->I)[at] : ((const conn_t *)nd->I)[at];
            mn = v < mn ? v : mn;
            mx = v > mx ? v : mx;
        }
    *lo = mx < 0 ? 0 : (Py_ssize_t)mn;
    *hi = mx < 0 ? 0 : (Py_ssize_t)mx + 1;
}

/* The worker threads kept between calls (_pool.c). */
int pool_begin(int nt);
double *pool_buffer(int t, size_t len);
void pool_run(int nt, void *(*fn)(void *), char *base, size_t size, double *const *zero, const size_t *zlen);
void pool_end(void);

/* Run worker(jobs[t]) for t < nt (job t of `size` bytes; its gradient pointer at byte `goff`), the first in
 * this thread, the others on the pool's threads (_pool.c; where another caller holds it, on threads made for
 * this call); no Python call (the XLA FFI handler below runs it on XLA's threads, without the GIL). `G` (length
 * `len` = 3 x nodes, or NULL): job 0 adds into it directly, the others into zeroed buffers added to it afterwards,
 * each over the range of the nodes of its items where `nd` gives them (else every node): a mesh numbered along
 * its elements gives each thread about 1/nt of the nodes (cube60_pert on 16 threads: 277 -> 206 MB resident), the
 * same sums in the same order. -1 if a buffer cannot be had (nothing run). */
static int run_jobs_nogil(void *jobs, size_t size, int nt, void *(*worker)(void *), double *G, Py_ssize_t len,
                          size_t goff, const Nodes *nd) {
    char *base = jobs;
    double *bufs[MAX_THREADS] = {0}, *zero[MAX_THREADS] = {0};
    size_t zlen[MAX_THREADS] = {0};
    int owned[MAX_THREADS] = {0}; /* a buffer of this call's own (else the pool's, zeroed by its worker) */
    Py_ssize_t span[MAX_THREADS][2] = {{0, 0}};
    int pooled = nt > 1 && pool_begin(nt);
    if (G) {
        *(double **)(base + goff) = G;
        for (int t = 1; t < nt; t++) {
            Py_ssize_t lo = 0, hi = len / 3;
            if (nd) node_span(nd, nd->items * t / nt, nd->items * (t + 1) / nt, &lo, &hi);
            span[t][0] = 3 * lo;
            span[t][1] = 3 * hi;
            size_t n = (size_t)(3 * (hi - lo));
            bufs[t] = pooled ? pool_buffer(t, n) : NULL;
            if (bufs[t]) {
                zero[t] = bufs[t];
                zlen[t] = n;
            } else {
                bufs[t] = calloc(n + 1, sizeof(double));
                owned[t] = 1;
            }
            if (!bufs[t]) {
                for (int k = 1; k < t; k++)
                    if (owned[k]) free(bufs[k]);
                if (pooled) pool_end();
                return -1;
            }
            /* the job writes node i's gradient at G[3 i + d]: its buffer's start stands for node lo */
            *(double **)(base + t * size + goff) = (double *)((uintptr_t)bufs[t] - (uintptr_t)(3 * lo) * sizeof(double));
        }
    }
    if (pooled) {
        pool_run(nt, worker, base, size, zero, zlen);
    } else {
        pthread_t tid[MAX_THREADS];
        int started[MAX_THREADS] = {0};
        for (int t = 1; t < nt; t++) started[t] = pthread_create(&tid[t], NULL, worker, base + t * size) == 0;
        worker(base);
        for (int t = 1; t < nt; t++) {
            if (started[t]) pthread_join(tid[t], NULL);
            else worker(base + t * size);  /* no thread to be had: this thread does that part too */
        }
    }
    if (G)
        for (int t = 1; t < nt; t++) {
            for (Py_ssize_t k = span[t][0]; k < span[t][1]; k++) G[k] += bufs[t][k - span[t][0]];
            if (owned[t]) free(bufs[t]);
        }
    if (pooled) pool_end();
    return 0;
}

/* run_jobs_nogil with the GIL released; -1 with MemoryError if a buffer cannot be had. */
static int run_jobs(void *jobs, size_t size, int nt, void *(*worker)(void *), double *G, Py_ssize_t len,
                    size_t goff, const Nodes *nd) {
    int rc;
    Py_BEGIN_ALLOW_THREADS
    rc = run_jobs_nogil(jobs, size, nt, worker, G, len, goff, nd);
    Py_END_ALLOW_THREADS
    if (rc < 0) PyErr_NoMemory();
    return rc;
}

typedef struct {
    Sums s;
    const double *P, *CW;
    const conn_t *H;
    double *T, *G;
    Py_ssize_t N, lo, hi;
    double weight;
    double *S; /* the corners' scaled Jacobians det / (|a| |b| |c|) (8, N), or NULL */
    double level, mu; /* mu > 0: the polish's penalty (hex_condition's docstring) */
    int cell_k; /* > 0: the polish's cell measure of power 2^cell_k in place of the corners' sum (the docstring) */
    const struct Lifted *L; /* non-NULL: the points are lifted from free coordinates as read (hex_condition_lifted) */
} HexJob;

/* x^(2^k) by k squarings (the same IEEE operations on every platform). */
static inline __attribute__((always_inline)) double pow2k(double x, int k) {
    for (int i = 0; i < k; i++) x *= x;
    return x;
}

/* x^(2^-k) by k square roots. */
static inline __attribute__((always_inline)) double root2k(double x, int k) {
    for (int i = 0; i < k; i++) x = sqrt(x);
    return x;
}

/* x86-64 with GCC: AVX-512 and AVX2 clones of the loops below beside the baseline one, picked at load time (the
 * eight corners of an element are the vector lanes: one AVX-512 vector). Every clone gives the same numbers bit
 * for bit: the same IEEE operations in the same order, no FMA contraction (-std=c99 keeps -ffp-contract=off). */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define VECTOR_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define VECTOR_CLONES
#endif

/* The columns a, b, c of the eight corners of a hexahedron whose node coordinates are X (X[d][k]: coordinate d of
 * local node k), times s: the corners side by side (structure of arrays: a[d][i] is coordinate d of corner i's
 * column a), as the loops below take them. */
static inline __attribute__((always_inline)) void columns_of(double X[3][8], double s, double a[3][8],
                                                             double b[3][8], double c[3][8]) {
    for (int d = 0; d < 3; d++)
        for (int i = 0; i < 8; i++) {
            a[d][i] = (X[d][NB[i][0]] - X[d][i]) * s;
            b[d][i] = (X[d][NB[i][1]] - X[d][i]) * s;
            c[d][i] = (X[d][NB[i][2]] - X[d][i]) * s;
        }
}

/* columns_of the hexahedron of nodes h, their coordinates read from the points P. */
static inline __attribute__((always_inline)) void hex_columns(const double *P, const conn_t *h, double s,
                                                              double a[3][8], double b[3][8], double c[3][8]) {
    double X[3][8];
    for (int k = 0; k < 8; k++)
        for (int d = 0; d < 3; d++) X[d][k] = P[3 * h[k] + d];
    columns_of(X, s, a, b, c);
}

/* The trial point's entry i, D[i] * alpha + V[i] (the product, then the sum: numpy's ``d * alpha`` then ``+= v``),
 * or V[i] without D. */
static inline __attribute__((always_inline)) double trial_at(const double *V, const double *D, double alpha,
                                                            Py_ssize_t i) {
    return D ? D[i] * alpha + V[i] : V[i];
}

/* One node's coordinates x0 + B (scale * v) (lift's numbers, bit for bit: the product, then the sum), its first
 * free coordinate s: an interior node's three, a surface node's two along its basis rows b (2, 3), an edge node's
 * one along its tangent t; of the trial point D * alpha + V with D. */
static inline __attribute__((always_inline)) void lift_interior_at(const double *x0, const double *SC,
                                                                  const double *V, const double *D, double alpha,
                                                                  Py_ssize_t s, double *out) {
    for (int d = 0; d < 3; d++) out[d] = x0[d] + SC[s + d] * trial_at(V, D, alpha, s + d);
}

static inline __attribute__((always_inline)) void lift_surface_at(const double *x0, const double *SC, const double *V,
                                                                 const double *D, double alpha, Py_ssize_t s,
                                                                 const double *b, double *out) {
    double u0 = SC[s] * trial_at(V, D, alpha, s), u1 = SC[s + 1] * trial_at(V, D, alpha, s + 1);
    for (int d = 0; d < 3; d++) out[d] = x0[d] + (u0 * b[d] + u1 * b[3 + d]);
}

static inline __attribute__((always_inline)) void lift_edge_at(const double *x0, const double *SC, const double *V,
                                                              const double *D, double alpha, Py_ssize_t s,
                                                              const double *t, double *out) {
    double u = SC[s] * trial_at(V, D, alpha, s);
    for (int d = 0; d < 3; d++) out[d] = x0[d] + u * t[d];
}

/* How many entries of the trial point D * alpha + V differ from V's (0 without D). */
static long long trial_moved(const double *V, const double *D, double alpha, Py_ssize_t m) {
    long long moved = 0;
    if (D)
        for (Py_ssize_t i = 0; i < m; i++) moved += trial_at(V, D, alpha, i) != V[i];
    return moved;
}

/* Node coordinates lifted from free coordinates where they are read, node by node (the helpers above), with no
 * (n, 3) array of them: slot[i] is node i's first free coordinate (-1: none, the node at x0), below os an interior
 * node's, below oe a surface node's (basis row (slot - os) / 2), else an edge node's (tangent row slot - oe). */
typedef struct Lifted {
    const double *X0, *SC, *V, *D, *SB, *ET;
    const int *slot;
    double alpha;
    Py_ssize_t os, oe;
} Lifted;

static inline __attribute__((always_inline)) void lifted_xyz(const Lifted *L, long long i, double out[3]) {
    const double *x0 = L->X0 + 3 * i;
    Py_ssize_t s = L->slot[i];
    if (__builtin_expect(s >= 0 && s < L->os, 1))  /* an interior node: most of them */
        lift_interior_at(x0, L->SC, L->V, L->D, L->alpha, s, out);
    else if (s < 0)
        for (int d = 0; d < 3; d++) out[d] = x0[d];
    else if (s < L->oe)
        lift_surface_at(x0, L->SC, L->V, L->D, L->alpha, s, L->SB + 3 * (s - L->os), out);
    else
        lift_edge_at(x0, L->SC, L->V, L->D, L->alpha, s, L->ET + 3 * (s - L->oe), out);
}

/* hex_columns of lifted points (s = 1). */
static inline __attribute__((always_inline)) void hex_columns_lifted(const Lifted *L, const conn_t *h,
                                                                     double a[3][8], double b[3][8], double c[3][8]) {
    double X[3][8];
    for (int k = 0; k < 8; k++) {
        double p[3];
        lifted_xyz(L, h[k], p);
        for (int d = 0; d < 3; d++) X[d][k] = p[d];
    }
    columns_of(X, 1.0, a, b, c);
}

/* x cross y of corner i (hex_columns' layout): its coordinate d into out[d * stride]. */
static inline __attribute__((always_inline)) void cross_at(double x[3][8], double y[3][8], int i, double *out,
                                                           int stride) {
    out[0] = x[1][i] * y[2][i] - x[2][i] * y[1][i];
    out[stride] = x[2][i] * y[0][i] - x[0][i] * y[2][i];
    out[2 * stride] = x[0][i] * y[1][i] - x[1][i] * y[0][i];
}

/* Elements [lo, hi) of hex_condition; the gradient into the job's own G (NULL: none). The eight corners of an
 * element are computed side by side (structure of arrays over the corners, so that the compiler vectorises
 * them); the sums run over the corners in order, as corner_term one corner at a time would. */
VECTOR_CLONES
static void *hex_worker(void *arg) {
    HexJob *j = arg;
    const double *P = j->P, *CW = j->CW;
    const conn_t *H = j->H;
    double *T = j->T, *G = j->G, *S = j->S, weight = j->weight, sum = 0.0, tmax = 0.0, level = j->level,
           mu = j->mu;
    int cell_k = j->cell_k;
    Py_ssize_t N = j->N;
    long long invalid = 0;
    for (Py_ssize_t e = j->lo; e < j->hi; e++) {
        const conn_t *h = H + 8 * e;
        double a[3][8], b[3][8], c[3][8], u[3][8], v[3][8], w[3][8];
        double det[8], fro2[8], adj2[8], idet[8], term[8], w2[8], p[8], q[8], r[8];
        if (j->L)
            hex_columns_lifted(j->L, h, a, b, c);
        else
            hex_columns(P, h, 1.0, a, b, c);
        for (int i = 0; i < 8; i++) {
            cross_at(b, c, i, &u[0][i], 8); cross_at(c, a, i, &v[0][i], 8); cross_at(a, b, i, &w[0][i], 8);
            det[i] = a[0][i] * u[0][i] + a[1][i] * u[1][i] + a[2][i] * u[2][i];
            fro2[i] = 0.0;
            adj2[i] = 0.0;
            for (int d = 0; d < 3; d++) {
                fro2[i] += a[d][i] * a[d][i] + b[d][i] * b[d][i] + c[d][i] * c[d][i];
                adj2[i] += u[d][i] * u[d][i] + v[d][i] * v[d][i] + w[d][i] * w[d][i];
            }
            idet[i] = 1.0 / (det[i] > 0.0 ? det[i] : 1.0);
            term[i] = det[i] > 0.0 ? fro2[i] * adj2[i] * (idet[i] * idet[i]) * (1.0 / 9.0) : INFINITY;
        }
        /* each corner's weight in the first sum: F's 1, or with the cell measure (cell_k > 0; M = t_max (mean_i
         * (t_i / t_max)^P)^(1/P), P = 2^cell_k) d (8 M) / d t_i = (t_i / M)^(P - 1) */
        double m = 0.0, one[8] = {1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0};
        if (cell_k > 0) {
            double top = 0.0, mean = 0.0;
            for (int i = 0; i < 8; i++) top = term[i] > top ? term[i] : top;
            for (int i = 0; i < 8; i++) mean += pow2k(term[i] / top, cell_k);
            m = top * root2k(mean * 0.125, cell_k);
            for (int i = 0; i < 8; i++) one[i] = pow2k(term[i] / m, cell_k) / (term[i] / m);
        }
        for (int i = 0; i < 8; i++) {
            int ok = det[i] > 0.0;
            double idet2 = idet[i] * idet[i];
            double over = mu > 0.0 && ok && term[i] - 1.0 > level ? term[i] - 1.0 - level : 0.0;
            w2[i] = ok && G ? (CW ? weight * CW[i * N + e] : weight * (one[i] + 2.0 * mu * over)) : 0.0;
            p[i] = w2[i] * adj2[i] * idet2;
            q[i] = w2[i] * fro2[i] * idet2;
            r[i] = p[i] * fro2[i] * idet[i];
        }
        if (S)
            for (int i = 0; i < 8; i++) {
                /* jaxci.metrics.elements._ratio: det / sqrt(|a|^2 |b|^2 |c|^2), 0 for a zero-length edge */
                double la = a[0][i] * a[0][i] + a[1][i] * a[1][i] + a[2][i] * a[2][i];
                double lb = b[0][i] * b[0][i] + b[1][i] * b[1][i] + b[2][i] * b[2][i];
                double lc = c[0][i] * c[0][i] + c[1][i] * c[1][i] + c[2][i] * c[2][i];
                double l2 = la * lb * lc;
                S[i * N + e] = l2 > 0.0 ? det[i] / sqrt(l2) : 0.0;
            }
        for (int i = 0; i < 8; i++) {
            if (T) T[i * N + e] = term[i];
            if (!(det[i] > 0.0)) {
                invalid++;
                continue;
            }
            double over = mu > 0.0 && term[i] - 1.0 > level ? term[i] - 1.0 - level : 0.0;
            sum += (cell_k > 0 ? m - 1.0 : term[i] - 1.0) + mu * over * over;
            if (term[i] > tmax) tmax = term[i];
        }
        if (!G) continue;
        double ga[3][8], gb[3][8], gc[3][8];
        for (int i = 0; i < 8; i++) {
            /* v x c + b x w, c x u + w x a, u x b + a x v (corner_term's) */
            double vxc[3], bxw[3], cxu[3], wxa[3], uxb[3], axv[3];
            cross_at(v, c, i, vxc, 1); cross_at(b, w, i, bxw, 1); cross_at(c, u, i, cxu, 1);
            cross_at(w, a, i, wxa, 1); cross_at(u, b, i, uxb, 1); cross_at(a, v, i, axv, 1);
            for (int d = 0; d < 3; d++) {
                ga[d][i] = p[i] * a[d][i] + q[i] * (vxc[d] + bxw[d]) - r[i] * u[d][i];
                gb[d][i] = p[i] * b[d][i] + q[i] * (cxu[d] + wxa[d]) - r[i] * v[d][i];
                gc[d][i] = p[i] * c[d][i] + q[i] * (uxb[d] + axv[d]) - r[i] * w[d][i];
            }
        }
        double g[8][3] = {{0.0}};
        for (int i = 0; i < 8; i++)
            for (int d = 0; d < 3; d++) {
                g[NB[i][0]][d] += ga[d][i];
                g[NB[i][1]][d] += gb[d][i];
                g[NB[i][2]][d] += gc[d][i];
                g[i][d] -= ga[d][i] + gb[d][i] + gc[d][i];
            }
        for (int k = 0; k < 8; k++)
            for (int d = 0; d < 3; d++) G[3 * h[k] + d] += g[k][d];
    }
    j->s = (Sums){sum, tmax, invalid};
    return NULL;
}

/* hex_condition(points (n, 3) f8, hexes (N, 8) i4, weight, grad (n, 3) f8 or None, corner_weight (8, N) f8 or
 * None, terms (8, N) f8 or None[, nthreads[, sj (8, N) f8 or None[, level, mu]]]) -> (sum of (term - 1), max term,
 * inverted corners). With `sj`, each corner's scaled Jacobian det / (|a| |b| |c|) (0 where an edge has length 0).
 * With mu > 0 (the worst-element polish's penalty, jaxci.optim.weighted.penalty_kernel, in one pass): the sum is
 * of e + mu max(0, e - level)^2 (e = term - 1) and, without corner_weight, each corner's gradient is weighted by
 * 1 + 2 mu max(0, e - level). With cell_k > 0 besides: each corner's e in the sum is the cell's M - 1 instead, M =
 * t_max (mean_i (t_i / t_max)^P)^(1/P) over the cell's eight terms, P = 2^cell_k (a smooth max of them: 8 M is
 * each cell's share, as 8 corners are in F's), and its gradient weight (t_i / M)^(P - 1) + 2 mu max(0, e - level).
 *
 * term = |A|^2 |adj A|^2 / (9 det^2) = (kappa/3)^2 per corner (inf where det <= 0, in `terms`). With `grad`, adds
 * weight * corner_weight[i, e] * (9/2) d term / d x of every valid corner to it: weight = 2 / (9 * 8N) gives the
 * gradient of F (w2 of jaxci.metrics.hexahedron._terms_and_grad), corner_weight the p-mean's (e_i / M_p)^(p - 1). */
/* hex_determinants(points (n, 3) f8, hexes (N, 8) i4, out (N, 8) f8) -> None: det A_i of every corner of every
 * hexahedron, with the arithmetic of jaxci.cells.corner_determinants' numpy loop (the same numbers, bit for bit:
 * the same differences, products and sums in the same order; C99 does not contract them into FMAs). */
static PyObject *hex_determinants(PyObject *self, PyObject *args) {
    static const Arg spec[3] = {{"points", "d"}, {"hexes", "i"}, {"out", "d", 1}};
    PyObject *o[3], *ret = NULL;
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2])) return NULL;
    Buf B[3] = {{{0}}};
    if (acquire_args(B, o, spec, 3) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, N = B[1].view.len / 32;
    if (B[0].view.len != n * 24 || B[1].view.len != N * 32 || B[2].view.len != N * 64) {
        PyErr_SetString(PyExc_ValueError, "hex_determinants: shapes disagree (points (n, 3), hexes (N, 8), out (N, 8))");
        goto done;
    }
    const conn_t *H = B[1].view.buf;
    if (check_conn(H, 8 * N, n, "hex_determinants") < 0) goto done;
    const double *P = B[0].view.buf;
    double *D = B[2].view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t e = 0; e < N; e++) { /* a . (b x c), numpy's order */
        double a[3][8], b[3][8], c[3][8], u[3][8];
        hex_columns(P, H + 8 * e, 1.0, a, b, c);
        for (int i = 0; i < 8; i++) {
            cross_at(b, c, i, &u[0][i], 8);
            D[8 * e + i] = a[0][i] * u[0][i] + a[1][i] * u[1][i] + a[2][i] * u[2][i];
        }
    }
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    release(B, 3);
    return ret;
}

static PyObject *hex_condition(PyObject *self, PyObject *args) {
    static const Arg spec[6] = {{"points", "d"}, {"hexes", "i"}, {"grad", "d", 1, 1}, {"corner_weight", "d", 0, 1},
                                {"terms", "d", 1, 1}, {"sj", "d", 1, 1}};
    PyObject *o[6] = {NULL, NULL, NULL, NULL, NULL, Py_None}, *ret = NULL;
    double weight, level = 0.0, mu = 0.0;
    int nthreads = 1, cell_k = 0;
    if (!PyArg_ParseTuple(args, "OOdOOO|iOddi", &o[0], &o[1], &weight, &o[2], &o[3], &o[4], &nthreads, &o[5], &level,
                          &mu, &cell_k))
        return NULL;
    if (cell_k < 0 || cell_k > 8) {
        PyErr_SetString(PyExc_ValueError, "hex_condition: cell_k must be in [0, 8]");
        return NULL;
    }
    Buf B[6] = {{{0}}};
    if (acquire_args(B, o, spec, 6) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, N = B[1].view.len / 32;
    if (B[0].view.len != n * 24 || B[1].view.len != N * 32 || (B[2].held && B[2].view.len != B[0].view.len) ||
        (B[3].held && B[3].view.len != N * 64) || (B[4].held && B[4].view.len != N * 64) ||
        (B[5].held && B[5].view.len != N * 64)) {
        PyErr_SetString(PyExc_ValueError, "hex_condition: shapes disagree (points (n, 3), hexes (N, 8), grad (n, 3), "
                                          "corner_weight, terms and sj (8, N))");
        goto done;
    }
    if (check_conn(B[1].view.buf, 8 * N, n, "hex_condition") < 0) goto done;
    HexJob jobs[MAX_THREADS];
    int nt = threads_for(N, nthreads, MIN_PER_THREAD);
    for (int t = 0; t < nt; t++)
        jobs[t] = (HexJob){{0.0, 0.0, 0}, B[0].view.buf, B[3].view.buf, B[1].view.buf, B[4].view.buf, NULL, N,
                           N * t / nt, N * (t + 1) / nt, weight, B[5].view.buf, level, mu, cell_k};
    Nodes nd = {B[1].view.buf, N, 8, 1, 8, 0};
    if (run_jobs(jobs, sizeof(HexJob), nt, hex_worker, B[2].view.buf, 3 * n, offsetof(HexJob, G), &nd) < 0) goto done;
    ret = total_sums(jobs, sizeof(HexJob), nt);
done:
    release(B, 6);
    return ret;
}

/* ---- hex_condition as an XLA FFI handler (jaxci.metrics.native_grad: the compiled JAX solvers on CPU) ----
 *
 * Built against XLA's own FFI C header as the installed jaxlib ships it (setup.py passes jax.ffi.include_dir()
 * and defines JAXCI_XLA_FFI where jax is importable at build time); without it the extension has no handler
 * (ffi_handler() returns None) and the compiled solvers keep XLA's kernel. ffi_api_version() is the API version
 * of the header it was built against, which jaxci.metrics.native_grad checks against the running jaxlib's. */
#ifdef JAXCI_XLA_FFI
#include "xla/ffi/api/c_api.h"

typedef XLA_FFI_Buffer XffiBuffer;

static XLA_FFI_Error *ffi_error(const XLA_FFI_CallFrame *cf, XLA_FFI_Error_Code errc, const char *message) {
    XLA_FFI_Error_Create_Args a = {XLA_FFI_Error_Create_Args_STRUCT_SIZE, NULL, message, errc};
    return cf->api->XLA_FFI_Error_Create(&a);
}

static int ffi_float(const XffiBuffer *b) { return b->dtype == XLA_FFI_DataType_F32 || b->dtype == XLA_FFI_DataType_F64; }

static double ffi_get(const XffiBuffer *b, Py_ssize_t k) {
    return b->dtype == XLA_FFI_DataType_F64 ? ((const double *)b->data)[k] : (double)((const float *)b->data)[k];
}

static void ffi_set(const XffiBuffer *b, Py_ssize_t k, double v) {
    if (b->dtype == XLA_FFI_DataType_F64) ((double *)b->data)[k] = v;
    else ((float *)b->data)[k] = (float)v;
}

/* Elements per chunk of an FFI job: their element-major node indices are copied to the stack (64 KB), never the
 * whole connectivity (640 MB at 10^7 hexahedra). */
#define FFI_CHUNK 1024

typedef struct {
    Sums s;
    const XffiBuffer *C, *W;
    const double *P;
    double *G;
    Py_ssize_t lo, hi;
    double weight;
} FfiJob;

/* Elements [lo, hi) of the FFI call, chunk by chunk through hex_worker, leaving out those of weight <= 0. */
static void *ffi_worker(void *arg) {
    FfiJob *j = arg;
    const XffiBuffer *C = j->C, *W = j->W;
    Py_ssize_t N = C->dims[1];
    conn_t H[8 * FFI_CHUNK];
    Sums s = {0.0, 0.0, 0};
    for (Py_ssize_t e0 = j->lo; e0 < j->hi; e0 += FFI_CHUNK) {
        Py_ssize_t e1 = e0 + FFI_CHUNK < j->hi ? e0 + FFI_CHUNK : j->hi, real = 0;
        for (Py_ssize_t e = e0; e < e1; e++) {
            if (!(ffi_get(W, e) > 0.0)) continue;
            for (int m = 0; m < 8; m++)
                H[8 * real + m] = C->dtype == XLA_FFI_DataType_S64 ? (conn_t)((const int64_t *)C->data)[m * N + e]
                                                                   : ((const int32_t *)C->data)[m * N + e];
            real++;
        }
        HexJob h = {{0.0, 0.0, 0}, j->P, NULL, H, NULL, j->G, real, 0, real, j->weight, NULL};
        hex_worker(&h);
        add_sum(&s, &h.s);
    }
    j->s = s;
    return NULL;
}

/* ffi_hex_terms_and_grad(points (n, 3), conn (8, N) s32/s64, weight (N,), params (2,)) -> (F, max kappa/3,
 * dF/dx (n, 3)), points, weight, params and the results all f32 or all f64: hex_condition in float64 over the
 * elements of weight > 0 (padding has weight 0), with F and its gradient divided by params[0] (0: the real
 * corners) and params[1] kernel threads. F and the max are inf if a corner has det <= 0 (the gradient leaves it
 * out). Node indices are the caller's own (jaxci.optim builds them): not checked here. */
static XLA_FFI_Error *ffi_hex_terms_and_grad(XLA_FFI_CallFrame *cf) {
    if (cf->extension_start && cf->extension_start->type == XLA_FFI_Extension_Metadata) {  /* which API, traits */
        XLA_FFI_Metadata *m = ((XLA_FFI_Metadata_Extension *)cf->extension_start)->metadata;
        m->api_version = (XLA_FFI_Api_Version){XLA_FFI_Api_Version_STRUCT_SIZE, NULL, XLA_FFI_API_MAJOR,
                                               XLA_FFI_API_MINOR};
        m->traits = 0;
        return NULL;
    }
    if (cf->stage != XLA_FFI_ExecutionStage_EXECUTE) return NULL;
    if (cf->args.size != 4 || cf->rets.size != 3)
        return ffi_error(cf, XLA_FFI_Error_Code_INVALID_ARGUMENT,
                         "jaxci_hex_terms_and_grad: expected 4 arguments and 3 results");
    const XffiBuffer *X = cf->args.args[0], *C = cf->args.args[1], *W = cf->args.args[2],
                     *Q = cf->args.args[3], *F = cf->rets.rets[0], *K = cf->rets.rets[1], *G = cf->rets.rets[2];
    if (X->rank != 2 || X->dims[1] != 3 || C->rank != 2 || C->dims[0] != 8 ||
        (C->dtype != XLA_FFI_DataType_S32 && C->dtype != XLA_FFI_DataType_S64) ||
        W->rank != 1 || W->dims[0] != C->dims[1] || Q->dtype != X->dtype || !ffi_float(X) || W->dtype != X->dtype ||
        F->dtype != X->dtype || K->dtype != X->dtype || G->dtype != X->dtype)
        return ffi_error(cf, XLA_FFI_Error_Code_INVALID_ARGUMENT,
                         "jaxci_hex_terms_and_grad: points (n, 3), conn (8, N) int, weight (N,), "
                         "params (2,); points, weight, params and results of one float type");
    Py_ssize_t n = X->dims[0], N = C->dims[1], real = 0;
    int f64 = X->dtype == XLA_FFI_DataType_F64;
    double count = ffi_get(Q, 0);
    if (!(count > 0.0)) {
        for (Py_ssize_t e = 0; e < N; e++) real += ffi_get(W, e) > 0.0;
        count = 8.0 * (double)real;
    }
    /* float64 points and gradient as they are; float32 ones through float64 copies */
    double *P = f64 ? X->data : malloc((size_t)(3 * n + 1) * sizeof(double));
    double *grad = f64 ? G->data : malloc((size_t)(3 * n + 1) * sizeof(double));
    if (!P || !grad) {
        if (!f64) { free(P); free(grad); }
        return ffi_error(cf, XLA_FFI_Error_Code_RESOURCE_EXHAUSTED, "jaxci_hex_terms_and_grad: out of memory");
    }
    if (!f64)
        for (Py_ssize_t k = 0; k < 3 * n; k++) P[k] = ffi_get(X, k);
    memset(grad, 0, (size_t)(3 * n) * sizeof(double));
    double weight = count > 0.0 ? 2.0 / (9.0 * count) : 0.0;
    FfiJob jobs[MAX_THREADS];
    int nt = threads_for(N, (int)ffi_get(Q, 1), MIN_PER_THREAD);
    for (int t = 0; t < nt; t++)
        jobs[t] = (FfiJob){{0.0, 0.0, 0}, C, W, P, NULL, N * t / nt, N * (t + 1) / nt, weight};
    int rc = run_jobs_nogil(jobs, sizeof(FfiJob), nt, ffi_worker, grad, 3 * n, offsetof(FfiJob, G), NULL);
    Sums s = add_sums(jobs, sizeof(FfiJob), nt);
    if (rc == 0) {
        int bad = s.invalid > 0;
        ffi_set(F, 0, bad ? INFINITY : (count > 0.0 ? s.sum / count : 0.0));
        ffi_set(K, 0, bad ? INFINITY : sqrt(s.tmax));
        if (!f64)
            for (Py_ssize_t k = 0; k < 3 * n; k++) ffi_set(G, k, grad[k]);
    }
    if (!f64) { free(P); free(grad); }
    return rc == 0 ? NULL : ffi_error(cf, XLA_FFI_Error_Code_RESOURCE_EXHAUSTED,
                                      "jaxci_hex_terms_and_grad: out of memory");
}

/* ffi_handler() -> a PyCapsule of ffi_hex_terms_and_grad, for jax.ffi.register_ffi_target. */
static PyObject *ffi_handler(PyObject *self, PyObject *args) {
    return PyCapsule_New((void *)ffi_hex_terms_and_grad, NULL, NULL);
}

/* ffi_api_version() -> (major, minor) of the XLA FFI header this extension was built against. */
static PyObject *ffi_api_version(PyObject *self, PyObject *args) {
    return Py_BuildValue("(ii)", XLA_FFI_API_MAJOR, XLA_FFI_API_MINOR);
}
#else
static PyObject *ffi_handler(PyObject *self, PyObject *args) { Py_RETURN_NONE; }
static PyObject *ffi_api_version(PyObject *self, PyObject *args) { Py_RETURN_NONE; }
#endif

typedef struct {
    Sums s;
    const double *P, *WI;
    const long long *T;
    double *TE, *G;
    Py_ssize_t C, lo, hi;
    double weight;
} CornerJob;

/* Corners [lo, hi) of corner_condition; the gradient into the job's own G (NULL: none). */
static void *corner_worker(void *arg) {
    CornerJob *j = arg;
    const double *P = j->P, *WI = j->WI;
    const long long *T = j->T;
    double *TE = j->TE, *G = j->G, w2 = G ? j->weight : 0.0, sum = 0.0, tmax = 0.0;
    Py_ssize_t C = j->C;
    long long invalid = 0;
    for (Py_ssize_t k = j->lo; k < j->hi; k++) {
        long long i[4] = {T[k], T[C + k], T[2 * C + k], T[3 * C + k]};
        double e[3][3], J[3][3], g[3][3], term;
        for (int m = 0; m < 3; m++)
            for (int d = 0; d < 3; d++) e[m][d] = P[3 * i[m + 1] + d] - P[3 * i[0] + d];
        for (int c = 0; c < 3; c++)  /* column c of J = A W^-1: sum_m (column m of A) W^-1[m][c] */
            for (int d = 0; d < 3; d++) J[c][d] = e[0][d] * WI[c] + e[1][d] * WI[3 + c] + e[2][d] * WI[6 + c];
        int ok = corner_term(J[0], J[1], J[2], w2, &term, g[0], g[1], g[2]);
        if (TE) TE[k] = term;
        if (!ok) {
            invalid++;
            continue;
        }
        sum += term - 1.0;
        if (term > tmax) tmax = term;
        if (w2 == 0.0) continue;
        for (int m = 0; m < 3; m++)  /* d/d(column m of A) = sum_c d/d(column c of J) W^-1[m][c] */
            for (int d = 0; d < 3; d++) {
                double gm = g[0][d] * WI[3 * m] + g[1][d] * WI[3 * m + 1] + g[2][d] * WI[3 * m + 2];
                G[3 * i[m + 1] + d] += gm;
                G[3 * i[0] + d] -= gm;
            }
    }
    j->s = (Sums){sum, tmax, invalid};
    return NULL;
}

/* corner_condition(points (n, 3) f8, table (4, C) i8, winv (3, 3) f8, weight, grad (n, 3) f8 or None, terms (C,)
 * f8 or None[, threads]) -> (sum of (term - 1), max term, inverted corners): hex_condition over a flat table of
 * corners (row 0 the corner's node, rows 1-3 the far ends of its columns) of any cell type, each corner matrix
 * taken relative to the type's ideal one, T = A W^-1 (jaxci.metrics.elements: wedges, pyramids, tetrahedra). */
static PyObject *corner_condition(PyObject *self, PyObject *args) {
    static const Arg spec[5] = {{"points", "d"}, {"table", "qlq"}, {"winv", "d"}, {"grad", "d", 1, 1},
                                {"terms", "d", 1, 1}};
    PyObject *o[5], *ret = NULL;
    double weight;
    int nthreads = 1;
    if (!PyArg_ParseTuple(args, "OOOdOO|i", &o[0], &o[1], &o[2], &weight, &o[3], &o[4], &nthreads)) return NULL;
    Buf B[5] = {{{0}}};
    if (acquire_args(B, o, spec, 5) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, C = B[1].view.len / 32;
    if (B[0].view.len != n * 24 || B[1].view.len != C * 32 || B[2].view.len != 72 ||
        (B[3].held && B[3].view.len != B[0].view.len) || (B[4].held && B[4].view.len != C * 8)) {
        PyErr_SetString(PyExc_ValueError, "corner_condition: shapes disagree (points (n, 3), table (4, C), winv "
                                          "(3, 3), grad (n, 3), terms (C,))");
        goto done;
    }
    if (check_indices(B[1].view.buf, 4 * C, n, "corner_condition") < 0) goto done;
    CornerJob jobs[MAX_THREADS];
    int nt = threads_for(C / 8, nthreads, MIN_PER_THREAD);
    for (int t = 0; t < nt; t++)
        jobs[t] = (CornerJob){{0.0, 0.0, 0}, B[0].view.buf, B[2].view.buf, B[1].view.buf, B[4].view.buf, NULL, C,
                              C * t / nt, C * (t + 1) / nt, weight};
    Nodes nd = {B[1].view.buf, C, 1, C, 4, 1};
    if (run_jobs(jobs, sizeof(CornerJob), nt, corner_worker, B[3].view.buf, 3 * n, offsetof(CornerJob, G), &nd) < 0)
        goto done;
    ret = total_sums(jobs, sizeof(CornerJob), nt);
done:
    release(B, 5);
    return ret;
}

typedef struct {
    const double *P, *IL;
    const conn_t *H;
    double *G;
    Py_ssize_t lo, hi;
    double eps, theta, energy, dmin;
} UntangleJob;

/* Elements [lo, hi) of untangle_energy; the gradient into the job's own G (NULL: none). As hex_worker: the eight
 * corners of an element side by side (structure of arrays), its eight nodes gathered and scattered once. */
VECTOR_CLONES
static void *untangle_worker(void *arg) {
    UntangleJob *j = arg;
    const double *P = j->P, *IL = j->IL;
    const conn_t *H = j->H;
    double *G = j->G, theta = j->theta, eps2 = j->eps * j->eps, energy = 0.0, dmin = INFINITY;
    for (Py_ssize_t e = j->lo; e < j->hi; e++) {
        const conn_t *h = H + 8 * e;
        double s_ = IL[e], a[3][8], b[3][8], c[3][8], u[3][8];
        double det[8], fro2[8], sq[8], ich[8], c23[8], shape[8], volume[8];
        hex_columns(P, h, s_, a, b, c);
        for (int i = 0; i < 8; i++) {
            cross_at(b, c, i, &u[0][i], 8);
            det[i] = a[0][i] * u[0][i] + a[1][i] * u[1][i] + a[2][i] * u[2][i];
            fro2[i] = 0.0;
            for (int d = 0; d < 3; d++) fro2[i] += a[d][i] * a[d][i] + b[d][i] * b[d][i] + c[d][i] * c[d][i];
            sq[i] = sqrt(eps2 + det[i] * det[i]);
            ich[i] = 1.0 / (det[i] >= 0.0 ? 0.5 * (det[i] + sq[i]) : 0.5 * eps2 / (sq[i] - det[i]));
        }
        for (int i = 0; i < 8; i++) {
            double r = cbrt(ich[i]);
            c23[i] = r * r;
        }
        for (int i = 0; i < 8; i++) {
            shape[i] = (1.0 - theta) * (fro2[i] / 3.0) * c23[i];
            volume[i] = theta * (det[i] * det[i] + 1.0) * ich[i];
        }
        for (int i = 0; i < 8; i++) {  /* in corner order, as the corner-by-corner sum */
            energy += shape[i] + volume[i];
            if (det[i] < dmin) dmin = det[i];
        }
        if (!G) continue;
        double g[8][3] = {{0.0}};
        for (int i = 0; i < 8; i++) {
            double p = (2.0 / 3.0) * (1.0 - theta) * c23[i] * s_;
            double q = ((-(2.0 / 3.0) * shape[i] - volume[i]) / sq[i] + 2.0 * theta * det[i] * ich[i]) * s_;
            double v[3], w[3];
            cross_at(c, a, i, v, 1); cross_at(a, b, i, w, 1);
            for (int d = 0; d < 3; d++) {
                double ga = p * a[d][i] + q * u[d][i], gb = p * b[d][i] + q * v[d], gc = p * c[d][i] + q * w[d];
                g[i][d] -= ga + gb + gc;
                g[NB[i][0]][d] += ga;
                g[NB[i][1]][d] += gb;
                g[NB[i][2]][d] += gc;
            }
        }
        for (int k = 0; k < 8; k++)
            for (int d = 0; d < 3; d++) G[3 * h[k] + d] += g[k][d];
    }
    j->energy = energy;
    j->dmin = dmin;
    return NULL;
}

/* untangle_energy(points (n, 3) f8, hexes (N, 8) i4, inv_len (N,) f8, eps, theta, grad (n, 3) f8 or None)
 * -> (sum of the corner energies, min det J): the regularised Winslow energy of
 * jaxci.optim._untangle_loop.hex_kernel over the hexahedra's corners, each element's columns scaled by its
 * inv_len (before the division by 32); with `grad`, d(sum)/dx is ADDED to it. */
static PyObject *untangle_energy(PyObject *self, PyObject *args) {
    static const Arg spec[4] = {{"points", "d"}, {"hexes", "i"}, {"inv_len", "d"}, {"grad", "d", 1, 1}};
    PyObject *o[4], *ret = NULL;
    double eps, theta;
    int nthreads = 1;
    if (!PyArg_ParseTuple(args, "OOOddO|i", &o[0], &o[1], &o[2], &eps, &theta, &o[3], &nthreads)) return NULL;
    Buf B[4] = {{{0}}};
    if (acquire_args(B, o, spec, 4) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, N = B[2].view.len / 8;
    if (B[0].view.len != n * 24 || B[1].view.len != N * 32 || (B[3].held && B[3].view.len != B[0].view.len)) {
        PyErr_SetString(PyExc_ValueError, "untangle_energy: shapes disagree (points (n, 3), hexes (N, 8), inv_len "
                                          "(N,), grad (n, 3))");
        goto done;
    }
    if (check_conn(B[1].view.buf, 8 * N, n, "untangle_energy") < 0) goto done;
    UntangleJob jobs[MAX_THREADS];
    int nt = threads_for(N, nthreads, MIN_PER_THREAD);
    for (int t = 0; t < nt; t++)
        jobs[t] = (UntangleJob){B[0].view.buf, B[2].view.buf, B[1].view.buf, NULL, N * t / nt, N * (t + 1) / nt,
                                eps, theta, 0.0, INFINITY};
    Nodes nd = {B[1].view.buf, N, 8, 1, 8, 0};
    if (run_jobs(jobs, sizeof(UntangleJob), nt, untangle_worker, B[3].view.buf, 3 * n, offsetof(UntangleJob, G),
                 &nd) < 0)
        goto done;
    double energy = 0.0, dmin = INFINITY;
    for (int t = 0; t < nt; t++) {
        energy += jobs[t].energy;
        if (jobs[t].dmin < dmin) dmin = jobs[t].dmin;
    }
    ret = Py_BuildValue("dd", energy, dmin);
done:
    release(B, 4);
    return ret;
}

/* ------------------------------------------------------------------------------------------ projection
 * The numpy path's boundary projection (jaxci.geometry.near.NearProjector): every active node to the nearest point
 * of its candidate triangles (segments), starting with the one of its hint. Tables as in jaxci.geometry._closest, one
 * cell's numbers together: (nc, TRI_ROWS) or (nc, SEG_ROWS), C order (the transpose of the module's (rows, nc) in
 * Fortran order, the same memory). A cell's quantities then share 3 cache lines instead of lying in 19 rows apart:
 * the local CI sweeps of Mesquite's cub_fru, whose trials each search a node's candidates, 26% faster. */
enum { TC = 0, TE1 = 3, TE2 = 6, TN = 9, TG = 12, TOK = 15, TIS = 16, TID = 17, TL2 = 18, TRI_ROWS = 19 };
enum { SA = 0, SD = 3, SI = 6, SL2 = 7, SEG_ROWS = 8 };

static inline double dot3(const double *u, const double *v) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

static inline double clip01(double t) { return t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t); }

/* Orthogonal projection of x onto the plane of triangle j into p; whether it falls inside (within tol). */
static int plane_point(const double *x, const double *T, Py_ssize_t j, double tol, double *p,
                       double *h, double *w, double *d1) {
#define R(r, k) T[j * TRI_ROWS + (r) + (k)]
    double e1[3] = {R(TE1, 0), R(TE1, 1), R(TE1, 2)}, e2[3] = {R(TE2, 0), R(TE2, 1), R(TE2, 2)};
    double un[3] = {R(TN, 0), R(TN, 1), R(TN, 2)};
    for (int d = 0; d < 3; d++) w[d] = x[d] - R(TC, d);
    *d1 = dot3(w, e1);
    double d2 = dot3(w, e2);
    double sb = R(TG, 0) * *d1 - R(TG, 1) * d2, rb = R(TG, 2) * d2 - R(TG, 1) * *d1;
    *h = dot3(w, un);
    for (int d = 0; d < 3; d++) p[d] = x[d] - *h * un[d];
    return R(TOK, 0) > 0.0 && sb >= -tol && rb >= -tol && sb + rb <= 1.0 + tol;
#undef R
}

/* The point q = o + t dir into p and its score (squared distance from x, plus penalty) into *best if that is below
 * *best. */
static inline void nearer_on_line(const double *x, const double *o, const double *dir, double t, double penalty,
                                  double *best, double *p) {
    double q[3], score = penalty;
    for (int d = 0; d < 3; d++) {
        q[d] = o[d] + t * dir[d];
        score += (x[d] - q[d]) * (x[d] - q[d]);
    }
    if (score < *best) {
        *best = score;
        for (int d = 0; d < 3; d++) p[d] = q[d];
    }
}

/* Nearest point of x on triangle j (jaxci.geometry._closest.closest_on_triangles): its score (squared distance, plus
 * a rounding-level penalty for points on the spoke or the side) and the point in p. */
static double closest_on_triangle(const double *x, const double *T, Py_ssize_t j, double tol,
                                  double bump, double *p) {
#define R(r, k) T[j * TRI_ROWS + (r) + (k)]
    double w[3], h, d1, best;
    int inside = plane_point(x, T, j, tol, p, &h, w, &d1);
    best = inside ? h * h : INFINITY;
    double penalty = bump * R(TL2, 0);
    double e1[3] = {R(TE1, 0), R(TE1, 1), R(TE1, 2)}, e2[3] = {R(TE2, 0), R(TE2, 1), R(TE2, 2)};
    double c[3] = {R(TC, 0), R(TC, 1), R(TC, 2)};
    nearer_on_line(x, c, e1, clip01(d1 * R(TIS, 0)), penalty, &best, p); /* the spoke */
    double side[3], we[3], ce[3];
    for (int d = 0; d < 3; d++) { side[d] = e2[d] - e1[d]; we[d] = w[d] - e1[d]; ce[d] = c[d] + e1[d]; }
    nearer_on_line(x, ce, side, clip01(dot3(we, side) * R(TID, 0)), penalty, &best, p); /* the side */
    return best;
#undef R
}

/* Nearest point of x on segment j (jaxci.geometry._closest.closest_on_segments); with `inside`, whether the orthogonal
 * projection falls inside it (jaxci.geometry._closest.line_point). */
static double closest_on_segment(const double *x, const double *T, Py_ssize_t j, double tol,
                                 double bump, double *p, int *inside) {
#define R(r, k) T[j * SEG_ROWS + (r) + (k)]
    double a[3] = {R(SA, 0), R(SA, 1), R(SA, 2)}, dv[3] = {R(SD, 0), R(SD, 1), R(SD, 2)}, inv = R(SI, 0);
    double xa[3] = {x[0] - a[0], x[1] - a[1], x[2] - a[2]};
    double s = dot3(xa, dv) * inv;
    *inside = inv > 0.0 && s >= -tol && s <= 1.0 + tol;
    double t = *inside ? s : clip01(s), d2 = 0.0;
    for (int d = 0; d < 3; d++) {
        p[d] = a[d] + t * dv[d];
        d2 += (x[d] - p[d]) * (x[d] - p[d]);
    }
    return *inside ? d2 : d2 + bump * R(SL2, 0);
#undef R
}

/* near_project(x (n, 3) f8, nodes (m,) i8, active (a,) i8, hint (m,) i8, cand (rows, K) i4, table (nt, R) f8,
 * spheres (nt, 4) f8 (each cell's bounding sphere: centre, radius), kind (0 triangles, 1 segments), tol, bump[,
 * nthreads]) -> None: moves x[nodes[i]] for every i of `active` to its nearest point among its K candidates
 * (hint[i] := its column): where the orthogonal projection onto its hint's cell falls inside, that unless a
 * candidate whose bounding sphere comes nearer holds a nearer point, else the best of them all. Up to nthreads
 * threads (default 1), each over its own active nodes. */
/* One point `xi` (in place) to the nearest point of its candidate cells CA[0..K) (columns of the table T of nc
 * cells; S their bounding spheres), starting from the remembered column *H (-1: none; updated): the search of
 * near_project for one node, shared with the local moves (ci_visit). */
/* Rows of a spheres table that also holds the spheres of the boundary faces (kind 0, 4 triangles a face: nc
 * triangle rows, then nc / 4 face rows, each holding its four triangles' spheres); -1 where there are none. */
static Py_ssize_t face_spheres(Py_ssize_t nc, int kind) { return kind == 0 && nc % 4 == 0 ? nc + nc / 4 : -1; }

static void project_one(double *xi, const int *CA, Py_ssize_t K, long long *H, const double *T, Py_ssize_t nc,
                        const double *S, const double *Q, int kind, double tol, double bump) {
    double p[3], h, w[3], d1;
    int inside = 0;
    if (*H >= 0) {
        Py_ssize_t j = CA[*H];
        double best;
        if (kind == 0) {
            inside = plane_point(xi, T, j, tol, p, &h, w, &d1);
            best = inside ? h * h : closest_on_triangle(xi, T, j, tol, bump, p);
        } else {
            best = closest_on_segment(xi, T, j, tol, bump, p, &inside);
        }
        /* another candidate may be nearer (a point inside its cell's prism near a concave part of the
         * boundary, or one that left the hint's cell): only one whose bounding sphere (S: centre, radius)
         * comes nearer than `best` can be, and for triangles one whose plane does; without this check the
         * projection jumped where the point left the prism, and the line search stalled there. The result
         * is the full search's nearest point, found among a few candidates. */
        double reach = sqrt(best);
        for (Py_ssize_t c = 0; c < K; c++) {
            if (Q && (CA[c] & 3) == 0 && c + 3 < K && CA[c + 1] == CA[c] + 1 && CA[c + 2] == CA[c] + 2 &&
                CA[c + 3] == CA[c] + 3) {
                /* the four triangles of one face: none comes nearer if the face's sphere (holding theirs) does
                 * not, so the four are passed over at once (the result is the same) */
                const double *qc = Q + 4 * (CA[c] >> 2);
                double dq2 = 0.0, limq = qc[3] + reach;
                for (int d = 0; d < 3; d++) dq2 += (xi[d] - qc[d]) * (xi[d] - qc[d]);
                if (dq2 > limq * limq) {
                    c += 3;
                    continue;
                }
            }
            const double *sc = S + 4 * CA[c];
            double dx2 = 0.0, q[3], slack = 1e-12 * sc[3], lim = sc[3] + reach + slack;
            if (c == *H) continue;
            for (int d = 0; d < 3; d++) dx2 += (xi[d] - sc[d]) * (xi[d] - sc[d]);
            if (dx2 > lim * lim) continue; /* ties stay: outside its cell, the first of equal ones is taken
                                              * (as the full search does); inside, the remembered one */
            if (kind == 0) {
                Py_ssize_t jc = CA[c];
                double hp = 0.0;
                for (int d = 0; d < 3; d++) hp += (xi[d] - T[jc * TRI_ROWS + TC + d]) * T[jc * TRI_ROWS + TN + d];
                if (fabs(hp) > reach + slack) continue; /* slack: rounding must not prune a tie at a vertex */
            }
            int in;
            double score = kind == 0 ? closest_on_triangle(xi, T, CA[c], tol, bump, q)
                                     : closest_on_segment(xi, T, CA[c], tol, bump, q, &in);
            if (score < best || (!inside && score == best && c < *H)) {
                best = score;
                reach = sqrt(best);
                *H = c;
                for (int d = 0; d < 3; d++) p[d] = q[d];
            }
        }
        inside = 1; /* found */
    }
    if (!inside) {
        double best = INFINITY, q[3];
        long long pick = 0;
        for (Py_ssize_t c = 0; c < K; c++) {
            int in;
            double score = kind == 0 ? closest_on_triangle(xi, T, CA[c], tol, bump, q)
                                     : closest_on_segment(xi, T, CA[c], tol, bump, q, &in);
            if (score < best || c == 0) {
                best = score;
                pick = c;
                for (int d = 0; d < 3; d++) p[d] = q[d];
            }
        }
        *H = pick;
    }
    for (int d = 0; d < 3; d++) xi[d] = p[d];
}

/* One thread's share of near_project: the active nodes [lo, hi) (each node's point and hint its own). */
typedef struct {
    double *X;
    const long long *N, *A;
    const int *CA;
    long long *H;
    const double *T, *S, *Q;
    Py_ssize_t K, nc, lo, hi;
    int kind;
    double tol, bump;
} ProjJob;

static void *project_worker(void *arg) {
    ProjJob *J = arg;
    for (Py_ssize_t k = J->lo; k < J->hi; k++) {
        Py_ssize_t i = J->A[k];
        project_one(J->X + 3 * J->N[i], J->CA + i * J->K, J->K, J->H + i, J->T, J->nc, J->S, J->Q, J->kind, J->tol,
                    J->bump);
    }
    return NULL;
}

/* Active nodes a thread of near_project gets at least (a node's search is ~0.1-0.5 us: a thread costs ~50 us). */
#define PROJECT_PER_THREAD 512

static PyObject *near_project(PyObject *self, PyObject *args) {
    static const Arg spec[7] = {{"x", "d", 1}, {"nodes", "qlq"}, {"active", "qlq"}, {"hint", "qlq", 1}, {"cand", "i"},
                                {"table", "d"}, {"spheres", "d"}};
    PyObject *o[7], *ret = NULL;
    int kind, nthreads = 1;
    double tol, bump;
    if (!PyArg_ParseTuple(args, "OOOOOOOidd|i", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &kind, &tol, &bump,
                          &nthreads))
        return NULL;
    Buf B[7] = {{{0}}};
    if (acquire_args(B, o, spec, 7) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8, na = B[2].view.len / 8;
    Py_ssize_t rows = kind == 0 ? TRI_ROWS : SEG_ROWS;
    Py_ssize_t nc = B[5].view.len / 8 / rows, K = B[4].view.ndim == 2 ? B[4].view.shape[1] : 0;
    const long long *N = B[1].view.buf, *A = B[2].view.buf;
    const int *CA = B[4].view.buf;
    long long *H = B[3].view.buf;
    if ((kind != 0 && kind != 1) || B[3].view.len != B[1].view.len || B[5].view.len != nc * rows * 8 || K < 1 ||
        B[4].view.len < m * K * 4 || (B[6].view.len != nc * 32 && B[6].view.len != face_spheres(nc, kind) * 32)) {
        PyErr_SetString(PyExc_ValueError, "near_project: shapes disagree");
        goto done;
    }
    if (check_indices(A, na, m, "near_project") < 0 || check_indices(N, m, n, "near_project") < 0 ||
        check_indices_of(CA, 4, m * K, nc, "near_project") < 0)
        goto done;
    for (Py_ssize_t k = 0; k < na; k++)
        if (H[A[k]] >= K) {
            PyErr_SetString(PyExc_IndexError, "near_project: hint out of range");
            goto done;
        }
    double *X = B[0].view.buf;
    const double *T = B[5].view.buf, *S = B[6].view.buf, *Q = B[6].view.len == nc * 32 ? NULL : S + 4 * nc;
    /* each active node's point and hint are its own (distinct nodes: `active` indexes distinct rows of `nodes`),
     * so the threads' shares are independent: the same result on any count */
    int nt = threads_for(na, nthreads, PROJECT_PER_THREAD);
    ProjJob jobs[MAX_THREADS];
    for (int t = 0; t < nt; t++)
        jobs[t] = (ProjJob){X, N, A, CA, H, T, S, Q, K, nc, na * t / nt, na * (t + 1) / nt, kind, tol, bump};
    if (run_jobs(jobs, sizeof(ProjJob), nt, project_worker, NULL, 0, 0, NULL) < 0) goto done;
    ret = Py_NewRef(Py_None);
done:
    release(B, 7);
    return ret;
}

/* The two-level preconditioner of jaxci.optim.coarse: q := M q = inv_diag * q + Z Cinv Z^T q, where free coordinate
 * i has coefficients z[i, 0..2] on coarse coordinates 3 block[i] + 0..2 (m of them; work: 2 m doubles). */
typedef struct {
    Py_ssize_t m;
    const long long *block;
    const double *z, *cinv, *idiag;
    double *work, gamma;
} Coarse;

static void coarse_apply(const Coarse *P, double *q, Py_ssize_t n) {
    double *c = P->work, *cc = P->work + P->m;
    for (Py_ssize_t j = 0; j < P->m; j++) c[j] = 0.0;
    for (Py_ssize_t i = 0; i < n; i++)
        for (int d = 0; d < 3; d++) c[3 * P->block[i] + d] += P->z[3 * i + d] * q[i];
    for (Py_ssize_t j = 0; j < P->m; j++) {
        const double *row = P->cinv + j * P->m;
        double acc[4] = {0.0, 0.0, 0.0, 0.0};
        for (Py_ssize_t l = 0; l < P->m; l++) acc[l & 3] += row[l] * c[l];
        cc[j] = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *zi = P->z + 3 * i, *ci = cc + 3 * P->block[i];
        q[i] = P->idiag[i] * q[i] + (zi[0] * ci[0] + zi[1] * ci[1] + zi[2] * ci[2]);
    }
}

/* Acquire the preconditioner's arrays o[0..3] (block (n,) i8, z (n, 3) f8, coarse_inv (mc, mc) f8, inv_diag (n,)
 * f8) into B[0..3], check them against n free coordinates and fill *pc, its work buffer allocated (the caller frees
 * pc->work and releases B, also on failure); -1 with the Python error set. `fn` names the caller in messages. */
static int coarse_acquire(Coarse *pc, Buf *B, PyObject *const *o, Py_ssize_t n, const char *fn) {
    static const Arg spec[4] = {{"block", "qlq"}, {"z", "d"}, {"coarse_inv", "d"}, {"inv_diag", "d"}};
    if (acquire_args(B, o, spec, 4) < 0) return -1;
    Py_ssize_t mc = (Py_ssize_t)(sqrt((double)(B[2].view.len / 8)) + 0.5);
    if (B[0].view.len != 8 * n || B[1].view.len != 24 * n || B[3].view.len != 8 * n || mc % 3 ||
        B[2].view.len != 8 * mc * mc) {
        PyErr_Format(PyExc_ValueError, "%s: preconditioner shapes disagree", fn);
        return -1;
    }
    if (check_indices(B[0].view.buf, n, mc / 3, fn) < 0) return -1;
    pc->m = mc;
    pc->block = B[0].view.buf;
    pc->z = B[1].view.buf;
    pc->cinv = B[2].view.buf;
    pc->idiag = B[3].view.buf;
    if (!(pc->work = PyMem_Malloc((size_t)(2 * mc + 1) * sizeof(double)))) {
        PyErr_NoMemory();
        return -1;
    }
    return 0;
}

/* The value of a float16 (IEEE binary16) `h`, exactly: its magnitude's bits moved into a float's and scaled by
 * 2^112 (the difference of the exponent biases; a subnormal half lands on a subnormal float first), then its
 * sign. */
static float half_value(uint16_t h) {
    uint32_t u = (uint32_t)(h & 0x7fffu) << 13;
    float f;
    memcpy(&f, &u, 4);
    f *= 0x1p112f;
    memcpy(&u, &f, 4);
    u |= (uint32_t)(h & 0x8000u) << 16;
    memcpy(&f, &u, 4);
    return f;
}

/* Every float16's value (filled at import, 256 kB): the two-loop recursion reads its pairs through it, 2.5x as
 * fast as converting each value in the loop (which the compiler does not vectorise). */
static float HALF[65536];

/* The two-loop recursion of lbfgs_direction over pairs stored as T (double, or float16 for a large memory, read
 * by PAIR_VALUE): q = -H g, the sums in double. A float16 row holds its pair's vector times a power of two; IS[slot] and
 * IY[slot] (NULL: 1) are their inverses, folded into each pass's scalar (c) and dot product, so that the passes
 * read the stored values alone. Each pass over the vectors updates q and takes the next pair's dot product with
 * the updated entries (one pass per pair instead of two), and every dot product is summed in four interleaved
 * partial sums: the dependent chain of one sum's additions bounded the loop (5,572 unknowns, 10 pairs: 0.18 ->
 * 0.05 ms; the same sums in another order, so the last bits of a direction differ from a single sum's). */
#define TWO_LOOP(NAME, T)                                                                                        \
    static void NAME(const double *G, const T *SS, const T *YY, const double *R, const long long *O,             \
                     const double *IS, const double *IY, Py_ssize_t k, Py_ssize_t n, double *q,                  \
                     const Coarse *PC) {                                                                         \
        double alpha[64], gamma = 1.0, c;                                                                        \
        Py_ssize_t n4 = n - n % 4;                                                                               \
        double d[4], dot; /* dot: v . q of the q already written (UPDATE_DOT) */                                 \
        const T *v = k ? SS + O[k - 1] * n : NULL, *x;                                                           \
        UPDATE_DOT(q[i] = G[i])                                                                                  \
        for (Py_ssize_t t = k - 1; t >= 0; t--) {                                                                \
            x = YY + O[t] * n;                                                                                   \
            c = -(alpha[t] = R[O[t]] * dot * (IS ? IS[O[t]] : 1.0)) * (IY ? IY[O[t]] : 1.0);                     \
            v = t ? SS + O[t - 1] * n : NULL;                                                                    \
            UPDATE_DOT(q[i] += c * PAIR_VALUE(x, i))                                                             \
        }                                                                                                        \
        if (PC) { /* H0 = gamma M, the two-level preconditioner; then the first forward dot */                   \
            coarse_apply(PC, q, n);                                                                              \
            const T *y0 = k ? YY + O[0] * n : NULL;                                                              \
            d[0] = d[1] = d[2] = d[3] = 0.0;                                                                     \
            for (Py_ssize_t i = 0; i < n; i++) {                                                                 \
                q[i] *= PC->gamma;                                                                               \
                if (y0) d[i & 3] += PAIR_VALUE(y0, i) * q[i];                                                    \
            }                                                                                                    \
            dot = (d[0] + d[1]) + (d[2] + d[3]);                                                                 \
        } else if (k) {                                                                                          \
            const T *s = SS + O[k - 1] * n, *y = YY + O[k - 1] * n;                                              \
            double sy[4] = {0.0, 0.0, 0.0, 0.0}, yy[4] = {0.0, 0.0, 0.0, 0.0};                                   \
            for (Py_ssize_t i = 0; i < n4; i += 4)                                                               \
                for (int j = 0; j < 4; j++) {                                                                    \
                    sy[j] += PAIR_VALUE(s, i + j) * PAIR_VALUE(y, i + j);                                        \
                    yy[j] += PAIR_VALUE(y, i + j) * PAIR_VALUE(y, i + j);                                        \
                }                                                                                                \
            for (Py_ssize_t i = n4; i < n; i++) {                                                                \
                sy[0] += PAIR_VALUE(s, i) * PAIR_VALUE(y, i);                                                    \
                yy[0] += PAIR_VALUE(y, i) * PAIR_VALUE(y, i);                                                    \
            }                                                                                                    \
            gamma = ((sy[0] + sy[1]) + (sy[2] + sy[3])) / ((yy[0] + yy[1]) + (yy[2] + yy[3]));                   \
            if (IS) gamma *= IS[O[k - 1]] / IY[O[k - 1]];                                                        \
            v = YY + O[0] * n;                                                                                   \
            UPDATE_DOT(q[i] *= gamma)                                                                            \
        }                                                                                                        \
        for (Py_ssize_t t = 0; t < k; t++) {                                                                     \
            x = SS + O[t] * n;                                                                                   \
            c = (alpha[t] - R[O[t]] * dot * (IY ? IY[O[t]] : 1.0)) * (IS ? IS[O[t]] : 1.0);                      \
            v = t + 1 < k ? YY + O[t + 1] * n : NULL;                                                            \
            UPDATE_DOT(q[i] += c * PAIR_VALUE(x, i))                                                             \
        }                                                                                                        \
        for (Py_ssize_t i = 0; i < n; i++) q[i] = -q[i];                                                         \
    }
/* STEP (q[i]'s update) for every i < n, then dot = v . q (the updated q) in four partial sums, 0 where v is
 * NULL. */
#define UPDATE_DOT(STEP)                                                                                         \
    d[0] = d[1] = d[2] = d[3] = 0.0;                                                                             \
    if (v) {                                                                                                     \
        for (Py_ssize_t i4 = 0; i4 < n4; i4 += 4)                                                                \
            for (int j = 0; j < 4; j++) {                                                                        \
                Py_ssize_t i = i4 + j;                                                                           \
                STEP;                                                                                            \
                d[j] += PAIR_VALUE(v, i) * q[i];                                                                 \
            }                                                                                                    \
        for (Py_ssize_t i = n4; i < n; i++) {                                                                    \
            STEP;                                                                                                \
            d[0] += PAIR_VALUE(v, i) * q[i];                                                                     \
        }                                                                                                        \
    } else {                                                                                                     \
        for (Py_ssize_t i = 0; i < n; i++) STEP;                                                                 \
    }                                                                                                            \
    dot = (d[0] + d[1]) + (d[2] + d[3]);
#define PAIR_VALUE(p, i) ((p)[i])
TWO_LOOP(two_loop_f8, double)
#undef PAIR_VALUE
#define PAIR_VALUE(p, i) ((double)HALF[(p)[i]])
TWO_LOOP(two_loop_f2, uint16_t)
#undef PAIR_VALUE
#undef TWO_LOOP
#undef UPDATE_DOT

/* lbfgs_direction(g (n,) f8, S (m, n) f8 or f2, Y (m, n) as S, rho (m,) f8, order (k,) i8, out (n,) f8
 *                 [, gamma, block (n,) i8, z (n, 3) f8, coarse_inv (mc, mc) f8, inv_diag (n,) f8, inv_scale (2, m) f8])
 *                 -> None:
 * out = -H g by the L-BFGS two-loop recursion over the pairs (S[i], Y[i], rho[i] = 1 / S[i].Y[i]) for i in
 * `order` (oldest first), the initial matrix scaled by s.y / y.y of the newest pair (jaxci.optim.host._direction),
 * or, given the preconditioner's arrays, gamma M (jaxci.optim.coarse; gamma from the caller).
 * float16 pairs: the memory of a large problem (jaxci.optim.host.HISTORY_F16_FROM), each row its vector times a
 * power of two whose inverses `inv_scale` gives (row 0: S's, row 1: Y's; required with float16 pairs); the
 * arithmetic in double. */
static PyObject *lbfgs_direction(PyObject *self, PyObject *args) {
    static const Arg spec[6] = {{"g", "d"}, {"S", "d"}, {"Y", "d"}, {"rho", "d"}, {"order", "qlq"}, {"out", "d", 1}},
                     spec_f2[2] = {{"S", "e"}, {"Y", "e"}}, spec_scale = {"inv_scale", "d"};
    PyObject *o[11] = {NULL, NULL, NULL, NULL, NULL, NULL, Py_None, Py_None, Py_None, Py_None, Py_None};
    PyObject *ret = NULL;
    double gamma = 1.0;
    if (!PyArg_ParseTuple(args, "OOOOOO|dOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &gamma, &o[6], &o[7],
                          &o[8], &o[9], &o[10]))
        return NULL;
    Buf B[11] = {{{0}}};
    Coarse pc = {0}, *PC = NULL;
    int f2 = 0;
    if (PyObject_CheckBuffer(o[1])) { /* float16 pairs? (the format decides which loop runs) */
        Py_buffer v;
        if (PyObject_GetBuffer(o[1], &v, PyBUF_FORMAT) == 0) {
            f2 = v.itemsize == 2 && v.format && v.format[0] == 'e' && v.format[1] == '\0';
            PyBuffer_Release(&v);
        } else {
            PyErr_Clear();
        }
    }
    if (acquire_args(B, o, spec, 1) < 0 || acquire_args(B + 1, o + 1, f2 ? spec_f2 : spec + 1, 2) < 0 ||
        acquire_args(B + 3, o + 3, spec + 3, 3) < 0 || (f2 && acquire_args(B + 10, o + 10, &spec_scale, 1) < 0))
        goto done;
    Py_ssize_t n = B[0].view.len / 8, m = B[3].view.len / 8, k = B[4].view.len / 8, w = f2 ? 2 : 8;
    const long long *O = B[4].view.buf;
    if (B[5].view.len != B[0].view.len || B[1].view.len != m * n * w || B[2].view.len != B[1].view.len || k > m ||
        k > 64 || (f2 && B[10].view.len != 2 * m * 8)) {
        PyErr_SetString(PyExc_ValueError, "lbfgs_direction: shapes disagree (or more than 64 pairs)");
        goto done;
    }
    if (check_indices(O, k, m, "lbfgs_direction") < 0) goto done;
    if (o[6] != Py_None) { /* the two-level preconditioner (jaxci.optim.coarse.CoarseSpace) */
        if (coarse_acquire(&pc, B + 6, o + 6, n, "lbfgs_direction (block)") < 0) goto done;
        pc.gamma = gamma;
        PC = &pc;
    }
    const double *G = B[0].view.buf, *R = B[3].view.buf, *IS = f2 ? B[10].view.buf : NULL, *IY = IS ? IS + m : NULL;
    double *q = B[5].view.buf;
    Py_BEGIN_ALLOW_THREADS
    if (f2)
        two_loop_f2(G, B[1].view.buf, B[2].view.buf, R, O, IS, IY, k, n, q, PC);
    else
        two_loop_f8(G, B[1].view.buf, B[2].view.buf, R, O, NULL, NULL, k, n, q, PC);
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    PyMem_Free(pc.work);
    release(B, 11);
    return ret;
}

/* half_dots(a (n,) f2, b (n,) f2) -> (a.b, a.a, b.b): the curvature sums of a float16 pair as stored (its
 * values' products exact in double, summed in double), one pass (numpy's einsum over float16 took 3 ms a sum at
 * 680,000 unknowns). */
static PyObject *half_dots(PyObject *self, PyObject *args) {
    static const Arg spec[2] = {{"a", "e"}, {"b", "e"}};
    PyObject *o[2];
    if (!PyArg_ParseTuple(args, "OO", &o[0], &o[1])) return NULL;
    Buf B[2] = {{{0}}};
    PyObject *ret = NULL;
    if (acquire_args(B, o, spec, 2) < 0) goto done;
    if (B[0].view.len != B[1].view.len) {
        PyErr_SetString(PyExc_ValueError, "half_dots: shapes disagree");
        goto done;
    }
    const uint16_t *a = B[0].view.buf, *b = B[1].view.buf;
    Py_ssize_t n = B[0].view.len / 2;
    double ab = 0.0, aa = 0.0, bb = 0.0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) {
        double x = HALF[a[i]], y = HALF[b[i]];
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    Py_END_ALLOW_THREADS
    ret = Py_BuildValue("(ddd)", ab, aa, bb);
done:
    release(B, 2);
    return ret;
}

/* coarse_apply(q (n,) f8, out (n,) f8, block (n,) i8, z (n, 3) f8, coarse_inv (mc, mc) f8, inv_diag (n,) f8) -> None:
 * out = M q, the two-level preconditioner of jaxci.optim.coarse (coarse_apply above). */
static PyObject *py_coarse_apply(PyObject *self, PyObject *args) {
    PyObject *o[6], *ret = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) return NULL;
    Buf B[6] = {{{0}}};
    Coarse pc = {0};
    static const Arg spec[2] = {{"q", "d"}, {"out", "d", 1}};
    if (acquire_args(B, o, spec, 2) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 8;
    if (B[1].view.len != 8 * n) {
        PyErr_SetString(PyExc_ValueError, "coarse_apply: q and out differ in length");
        goto done;
    }
    if (coarse_acquire(&pc, B + 2, o + 2, n, "coarse_apply (block)") < 0) goto done;
    double *out = B[1].view.buf;
    const double *q = B[0].view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++) out[i] = q[i];
    coarse_apply(&pc, out, n);
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    PyMem_Free(pc.work);
    release(B, 6);
    return ret;
}

/* ------------------------------------------------------------------------------------------ local moves
 * A node's star is its incidences: inc[m, k] = 8 e + s for the k-th element e around node slot m, the node being
 * that element's local node s (jaxci.optim._local.node_stars); rot (8,8) is jaxci.cells.ROTATE_TO_SLOT, which
 * relabels the element so that the node is its local node 0 (8x less memory than the relabelled node lists; the
 * nodes are read through it as each element is set up).
 * local_sums(points (n,3) f8, hexes (N,8) i4, rot (8,8) i8, inc (M,K) i8, count (M,) i8, trials (M,S,3) f8,
 * out (M,S) f8[, nthreads]) -> None: for node slot m with its first count[m] star elements and the node at
 * trials[m, s], out[m, s] = the sum of (kappa/3)^2 over the four corners of each element whose matrix holds slot 0
 * (AFFECTED_CORNERS of jaxci.optim._local), inf if one has det <= 0: jaxci.optim._local.local_terms, one pass.
 * Per node, every such corner's term is set up once as a polynomial of the node's displacement (poly_setup), which
 * each trial then evaluates (poly_sums). */

/* What one element of a node's star holds fixed while the node (its local slot 0) moves: the nodes of corner 0's
 * columns, and for corners 1, 3 and 4 their two fixed columns, the cross product F of those (det = the moving
 * column . F) and their squared norms. */
typedef struct {
    double P1[3], P3[3], P4[3], a1[3], c1[3], F1[3], b3[3], c3[3], F3[3], a4[3], b4[3], F4[3], r1, r3, r4, n1, n3, n4;
} Elem;

/* The nodes e[0..7] of incidence `inc` (8 x element + local node), relabelled by `rot` so that the node is 0. */
static inline void star_nodes(const conn_t *HEX, const long long *ROT, long long inc, long long *e) {
    const conn_t *h = HEX + 8 * (inc / 8);
    const long long *r = ROT + 8 * (inc % 8);
    for (int j = 0; j < 8; j++) e[j] = h[r[j]];
}

/* 0 if rot (8,8) holds local nodes, every count[m] is in [0, K] and every incidence inc[m, k < count[m]] names an
 * element of hexes (N,8) whose nodes are in [0, n); else -1 with an IndexError naming the function. */
static int check_stars(const conn_t *HEX, Py_ssize_t N, Py_ssize_t n, const long long *ROT, const long long *INC,
                       const long long *CNT, Py_ssize_t M, Py_ssize_t K, const char *fn) {
    for (int k = 0; k < 64; k++)
        if (ROT[k] < 0 || ROT[k] > 7) {
            PyErr_Format(PyExc_IndexError, "%s: rot holds %lld, not a local node 0-7", fn, ROT[k]);
            return -1;
        }
    for (Py_ssize_t m = 0; m < M; m++) {
        if (CNT[m] < 0 || CNT[m] > K) {
            PyErr_Format(PyExc_IndexError, "%s: count %lld out of range [0, %zd]", fn, CNT[m], K);
            return -1;
        }
        for (Py_ssize_t k = 0; k < CNT[m]; k++) {
            long long i = INC[m * K + k];
            if (i < 0 || i >= 8 * N) {
                PyErr_Format(PyExc_IndexError, "%s: incidence %lld out of range [0, %zd)", fn, i, 8 * N);
                return -1;
            }
            if (check_conn(HEX + 8 * (i / 8), 8, n, fn) < 0) return -1;
        }
    }
    return 0;
}

static void elem_setup(const double *X, const conn_t *HEX, const long long *ROT, long long inc, Elem *E) {
    long long e[8];
    star_nodes(HEX, ROT, inc, e);
    const double *P1 = X + 3 * e[1], *P2 = X + 3 * e[2], *P3 = X + 3 * e[3], *P4 = X + 3 * e[4],
                 *P5 = X + 3 * e[5], *P7 = X + 3 * e[7];
    for (int d = 0; d < 3; d++) {
        E->P1[d] = P1[d]; E->P3[d] = P3[d]; E->P4[d] = P4[d];
        E->a1[d] = P2[d] - P1[d]; E->c1[d] = P5[d] - P1[d];
        E->b3[d] = P2[d] - P3[d]; E->c3[d] = P7[d] - P3[d];
        E->a4[d] = P7[d] - P4[d]; E->b4[d] = P5[d] - P4[d];
    }
    cross(E->c1, E->a1, E->F1); cross(E->b3, E->c3, E->F3); cross(E->a4, E->b4, E->F4);
    E->r1 = dot3(E->a1, E->a1) + dot3(E->c1, E->c1);
    E->r3 = dot3(E->b3, E->b3) + dot3(E->c3, E->c3);
    E->r4 = dot3(E->a4, E->a4) + dot3(E->b4, E->b4);
    E->n1 = dot3(E->F1, E->F1); E->n3 = dot3(E->F3, E->F3); E->n4 = dot3(E->F4, E->F4);
}

/* A node's local objective as polynomials of its displacement d = y - x0 (ci_visit). Every corner that moves with
 * the node has |A|^2, |adj A|^2 quadratic and det affine in d (a column moves by d, or all three do: det is then
 * 6 x the volume of the tetrahedron (y, P1, P3, P4), affine too), so each corner's term |A|^2 |adj A|^2 / det^2
 * comes from POLY_ROWS numbers set up once per visit (poly_setup): row 0 gamma, 1-3 beta, 4 alpha of
 * |A|^2 = gamma + beta.d + alpha |d|^2; 5 D0, 6-8 g of det = D0 + g.d; 9 c, 10-12 l, 13-18 the quadratic form
 * (d0^2, d1^2, d2^2, d0 d1, d0 d2, d1 d2) of |adj A|^2. Rows of NP corners (the real ones, then padding with
 * |A|^2 = 0, det = 1: a term 0). A trial then costs 16 multiply-adds and a division per corner, where the
 * corner's matrices cost about 60 operations, and the corners are the vector lanes. */
#define POLY_ROWS 19
#define POLY_LANES 8

/* The corners of a star of cnt elements, padded to a whole number of vectors: the row length NP of poly_setup. */
static inline Py_ssize_t poly_width(Py_ssize_t cnt) { return (4 * cnt + POLY_LANES - 1) / POLY_LANES * POLY_LANES; }

/* Corner j of the rows P (NP corners each) from |A|^2 = gamma + beta.d + alpha |d|^2, det = D0 + g.d and
 * |adj A|^2 = c + 2 m.d + d^T Q d (Q symmetric: q00 q11 q22 q01 q02 q12). */
static inline void poly_put(double *P, Py_ssize_t NP, Py_ssize_t j, double gamma, const double *beta, double alpha,
                     double D0, const double *g, double c, const double *m, const double *Q) {
    double row[POLY_ROWS] = {gamma, beta[0], beta[1], beta[2], alpha, D0, g[0], g[1], g[2], c,
                             2.0 * m[0], 2.0 * m[1], 2.0 * m[2], Q[0], Q[1], Q[2], 2.0 * Q[3], 2.0 * Q[4], 2.0 * Q[5]};
    for (int r = 0; r < POLY_ROWS; r++) P[r * NP + j] = row[r];
}

/* Q += |e|^2 I - e e^T, the quadratic form of |z x e|^2 in z. */
static inline void add_cross_form(double *Q, const double *e) {
    double e2 = dot3(e, e);
    Q[0] += e2 - e[0] * e[0]; Q[1] += e2 - e[1] * e[1]; Q[2] += e2 - e[2] * e[2];
    Q[3] -= e[0] * e[1]; Q[4] -= e[0] * e[2]; Q[5] -= e[1] * e[2];
}

/* A corner with one moving column z = z0 + d and fixed columns e1, e2 (r = |e1|^2 + |e2|^2, F their cross product
 * with det = z.F, n = |F|^2): |A|^2 = r + |z|^2, |adj A|^2 = n + |z x e1|^2 + |z x e2|^2. */
static inline void poly_one_column(double *P, Py_ssize_t NP, Py_ssize_t j, const double *z0, double r, const double *F,
                            double n, const double *e1, const double *e2) {
    double Q[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0}, beta[3], m[3];
    add_cross_form(Q, e1);
    add_cross_form(Q, e2);
    m[0] = Q[0] * z0[0] + Q[3] * z0[1] + Q[4] * z0[2];
    m[1] = Q[3] * z0[0] + Q[1] * z0[1] + Q[5] * z0[2];
    m[2] = Q[4] * z0[0] + Q[5] * z0[1] + Q[2] * z0[2];
    for (int d = 0; d < 3; d++) beta[d] = 2.0 * z0[d];
    poly_put(P, NP, j, r + dot3(z0, z0), beta, 1.0, dot3(z0, F), F, n + dot3(z0, m), m, Q);
}

/* The rows P (NP >= 4 cnt corners) of the star E[0..cnt) of a node at x0. */
static void poly_setup(const Elem *E, Py_ssize_t cnt, const double *x0, double *P, Py_ssize_t NP) {
    static const double zero[3] = {0.0, 0.0, 0.0};
    for (Py_ssize_t k = 0; k < cnt; k++) {
        const Elem *e = E + k;
        /* corner 0: columns a = P1 - y, b = P3 - y, c = P4 - y, all moving by -d */
        double a[3], b[3], c[3], u[3], v[3], w[3], e1[3], e2[3], e3[3], t[3], beta[3], g[3], m[3];
        double Q[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        for (int d = 0; d < 3; d++) { a[d] = e->P1[d] - x0[d]; b[d] = e->P3[d] - x0[d]; c[d] = e->P4[d] - x0[d]; }
        cross(b, c, u); cross(c, a, v); cross(a, b, w);
        for (int d = 0; d < 3; d++) {
            beta[d] = -2.0 * (a[d] + b[d] + c[d]);
            g[d] = -(u[d] + v[d] + w[d]);
            e1[d] = c[d] - b[d]; e2[d] = a[d] - c[d]; e3[d] = b[d] - a[d];
            m[d] = 0.0;
        }
        /* u(d) = u + e1 x d: |u(d)|^2 = |u|^2 + 2 (u x e1).d + |d x e1|^2; likewise v with e2, w with e3 */
        cross(u, e1, t); for (int d = 0; d < 3; d++) m[d] += t[d];
        cross(v, e2, t); for (int d = 0; d < 3; d++) m[d] += t[d];
        cross(w, e3, t); for (int d = 0; d < 3; d++) m[d] += t[d];
        add_cross_form(Q, e1); add_cross_form(Q, e2); add_cross_form(Q, e3);
        poly_put(P, NP, 4 * k, dot3(a, a) + dot3(b, b) + dot3(c, c), beta, 3.0, dot3(a, u), g,
                 dot3(u, u) + dot3(v, v) + dot3(w, w), m, Q);
        /* corners 1, 3, 4: one column y - P moving by d */
        double z[3];
        for (int d = 0; d < 3; d++) z[d] = x0[d] - e->P1[d];
        poly_one_column(P, NP, 4 * k + 1, z, e->r1, e->F1, e->n1, e->c1, e->a1);
        for (int d = 0; d < 3; d++) z[d] = x0[d] - e->P3[d];
        poly_one_column(P, NP, 4 * k + 2, z, e->r3, e->F3, e->n3, e->c3, e->b3);
        for (int d = 0; d < 3; d++) z[d] = x0[d] - e->P4[d];
        poly_one_column(P, NP, 4 * k + 3, z, e->r4, e->F4, e->n4, e->b4, e->a4);
    }
    for (Py_ssize_t j = 4 * cnt; j < NP; j++) poly_put(P, NP, j, 0.0, zero, 0.0, 1.0, zero, 0.0, zero, zero);
}

/* The monomials of a displacement d: d0, d1, d2, |d|^2, d0^2, d1^2, d2^2, d0 d1, d0 d2, d1 d2. */
static inline void poly_monomials(const double *Y, int S, int s, const double *x0, double *m) {
    const double d0 = Y[s] - x0[0], d1 = Y[S + s] - x0[1], d2 = Y[2 * S + s] - x0[2];
    m[0] = d0; m[1] = d1; m[2] = d2; m[3] = d0 * d0 + d1 * d1 + d2 * d2;
    m[4] = d0 * d0; m[5] = d1 * d1; m[6] = d2 * d2; m[7] = d0 * d1; m[8] = d0 * d2; m[9] = d1 * d2;
}

/* The term 9 (kappa/3)^2 of the corner at p (a pointer into the rows P, NP apart) for the monomials m; inf if
 * det <= 0 (selected after the division, so that the loop stays branch-free). */
static inline __attribute__((always_inline)) double poly_term(const double *p, Py_ssize_t NP, const double *m) {
    double A = p[0] + p[NP] * m[0] + p[2 * NP] * m[1] + p[3 * NP] * m[2] + p[4 * NP] * m[3];
    double B = p[9 * NP] + p[10 * NP] * m[0] + p[11 * NP] * m[1] + p[12 * NP] * m[2] + p[13 * NP] * m[4] +
               p[14 * NP] * m[5] + p[15 * NP] * m[6] + p[16 * NP] * m[7] + p[17 * NP] * m[8] + p[18 * NP] * m[9];
    double D = p[5 * NP] + p[6 * NP] * m[0] + p[7 * NP] * m[1] + p[8 * NP] * m[2];
    double q = A * B / (D * D);
    return D > 0.0 ? q : INFINITY;
}

/* The sums of (kappa/3)^2 over a node's corners (the rows P of poly_setup at x0, NP a multiple of POLY_LANES) at S
 * trial positions (Y: 3 x S, structure of arrays) into f (S,), inf where a corner has det <= 0. Each trial's sum in
 * lanes, the lanes added in order. */
VECTOR_CLONES
static void poly_sums(const double *restrict P, Py_ssize_t NP, const double *restrict x0, const double *restrict Y,
                      int S, double *restrict f) {
    for (int s = 0; s < S; s++) {
        double m[10], acc[POLY_LANES] = {0.0};
        poly_monomials(Y, S, s, x0, m);
        for (Py_ssize_t j = 0; j < NP; j += POLY_LANES)
            for (int l = 0; l < POLY_LANES; l++) acc[l] += poly_term(P + j + l, NP, m);
        double total = 0.0;
        for (int l = 0; l < POLY_LANES; l++) total += acc[l];
        f[s] = total * (1.0 / 9.0);
    }
}

/* One thread's node slots [lo, hi) of local_sums, with its own work buffers (failed: none could be had). */
typedef struct {
    const double *X, *TR;
    const conn_t *HEX;
    const long long *ROT, *INC, *CNT;
    double *OUT;
    Py_ssize_t K, S, lo, hi;
    int failed;
} SumsJob;

static void *local_sums_worker(void *arg) {
    SumsJob *J = arg;
    const Py_ssize_t K = J->K, S = J->S;
    Elem *E = malloc(sizeof(Elem) * (K ? K : 1));
    double *P = malloc(sizeof(double) * POLY_ROWS * (size_t)(K ? poly_width(K) : POLY_LANES));
    double *Y = malloc(sizeof(double) * 3 * (size_t)(S ? S : 1));
    if (!E || !P || !Y) {
        J->failed = 1;
        free(E); free(P); free(Y);
        return NULL;
    }
    for (Py_ssize_t m = J->lo; m < J->hi; m++) {
        double *o = J->OUT + m * S;
        const double *tr = J->TR + 3 * m * S;
        Py_ssize_t cnt = J->CNT[m], NP = poly_width(cnt);
        if (cnt == 0) {
            for (Py_ssize_t s = 0; s < S; s++) o[s] = 0.0;
            continue;
        }
        long long e[8];
        star_nodes(J->HEX, J->ROT, J->INC[m * K], e);
        for (Py_ssize_t k = 0; k < cnt; k++) elem_setup(J->X, J->HEX, J->ROT, J->INC[m * K + k], &E[k]);
        poly_setup(E, cnt, J->X + 3 * e[0], P, NP);
        for (Py_ssize_t s = 0; s < S; s++)
            for (int d = 0; d < 3; d++) Y[d * S + s] = tr[3 * s + d];
        poly_sums(P, NP, J->X + 3 * e[0], Y, (int)S, o);
    }
    free(E); free(P); free(Y);
    return NULL;
}

static PyObject *local_sums(PyObject *self, PyObject *args) {
    static const Arg spec[7] = {{"points", "d"}, {"hexes", "i"}, {"rot", "qlq"}, {"inc", "qlq"}, {"count", "qlq"},
                                {"trials", "d"}, {"out", "d", 1}};
    PyObject *o[7], *ret = NULL;
    int nthreads = 1;
    if (!PyArg_ParseTuple(args, "OOOOOOO|i", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &nthreads)) return NULL;
    Buf B[7] = {{{0}}};
    if (acquire_args(B, o, spec, 7) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, N = B[1].view.len / 32, M = B[4].view.len / 8,
               S = M ? B[6].view.len / 8 / M : 0, K = M ? B[3].view.len / 8 / M : 0;
    if (B[0].view.len != n * 24 || B[1].view.len != N * 32 || B[2].view.len != 512 || B[3].view.len != M * K * 8 ||
        B[5].view.len != M * S * 24 || B[6].view.len != M * S * 8) {
        PyErr_SetString(PyExc_ValueError, "local_sums: shapes disagree (points (n, 3), hexes (N, 8), rot (8, 8), "
                                          "inc (M, K), count (M,), trials (M, S, 3), out (M, S))");
        goto done;
    }
    const conn_t *HEX = B[1].view.buf;
    const long long *ROT = B[2].view.buf, *INC = B[3].view.buf, *CNT = B[4].view.buf;
    if (check_stars(HEX, N, n, ROT, INC, CNT, M, K, "local_sums") < 0) goto done;
    /* the node slots split into fixed ranges, each slot's sums computed alone: the same numbers on any count */
    int nt = threads_for(M, nthreads, 256);
    SumsJob jobs[MAX_THREADS];
    for (int j = 0; j < nt; j++)
        jobs[j] = (SumsJob){B[0].view.buf, B[5].view.buf, HEX, ROT, INC, CNT, B[6].view.buf, K, S, M * j / nt,
                            M * (j + 1) / nt, 0};
    if (run_jobs(jobs, sizeof(SumsJob), nt, local_sums_worker, NULL, 0, 0, NULL) < 0) goto done;
    for (int j = 0; j < nt; j++)
        if (jobs[j].failed) {
            PyErr_NoMemory();
            goto done;
        }
    ret = Py_NewRef(Py_None);
done:
    release(B, 7);
    return ret;
}

/* ------------------------------------------------------------------------------------------ local CI
 * ci_visit: one cohort run of local CI for every node of one colour (jaxci.optim.host_local, the algorithm of
 * jaxci.optim.ci._local_ci_colour), in place on x (n,3) and width (n,); returns the number of nodes moved.
 * Nodes of one colour share no element, so each node's cohort runs alone, against the current x. Random numbers:
 * xoshiro256** seeded by splitmix64 from `seed`. */
typedef struct {
    unsigned long long s[4];
} Rng;

static unsigned long long splitmix(unsigned long long *x) {
    unsigned long long z = (*x += 0x9e3779b97f4a7c15ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
}

static inline unsigned long long rotl(unsigned long long x, int k) { return (x << k) | (x >> (64 - k)); }

static inline double xoshiro(Rng *r) { /* [0, 1) */
    unsigned long long *s = r->s, out = rotl(s[1] * 5, 7) * 9, t = s[1] << 17;
    s[2] ^= s[0]; s[3] ^= s[1]; s[1] ^= s[2]; s[0] ^= s[3]; s[2] ^= t; s[3] = rotl(s[3], 45);
    return (double)(out >> 11) * 0x1.0p-53;
}

/* The counter stream of jaxci.optim._draws (its `mix` and float64 `uniforms`; C cannot call them): the numbers
 * the JAX engine draws with stream="counter", checked against them in tests/test_ci_parity.py. */
static inline unsigned int mix32(unsigned int h, unsigned int v) {
    h ^= v * 0x9E3779B1u;
    h ^= h >> 16; h *= 0x85EBCA6Bu; h ^= h >> 13; h *= 0xC2B2AE35u;
    return h ^ (h >> 16);
}

static inline double counter_uniform(unsigned int h, unsigned int i) {
    unsigned int a = mix32(h, 2u * i) >> 5, b = mix32(h, 2u * i + 1u) >> 6;
    return ((double)a * 67108864.0 + (double)b) * (1.0 / 9007199254740992.0);
}

/* A node's uniforms in [0, 1): its own xoshiro256** stream, or (counter) the draw `what` (0 the roulette, 1 the
 * trials) of learning attempt `a` at the node's word `h`, index i. */
typedef struct {
    Rng rng;
    int counter;
    unsigned int h;
} Draws;

static inline double uniform(Draws *r, int a, int what, int i) {
    return r->counter ? counter_uniform(mix32(mix32(r->h, (unsigned int)a), (unsigned int)what), (unsigned int)i)
                      : xoshiro(&r->rng);
}

/* The cell tables of one boundary kind: candidate columns (rows x K), table (nc cells), spheres. */
typedef struct {
    const int *cand;
    Py_ssize_t rows, K, nc;
    const double *table, *spheres, *faces; /* faces: the face spheres after the triangles' (kind 0), or NULL */
    long long *hint;
} Cells;

/* One ci_visit call's arguments, shared by its threads (each over its own range of node slots). */
typedef struct {
    double *X, *WIDTH;
    const double *BASIS, *FREE, *PLANE;
    const long long *NODES;
    const conn_t *HEX;
    const long long *ROT, *INC, *CNT, *ROW, *KIND;
    Cells *cells;
    Py_ssize_t K, lo, hi;
    int C, t, T, n_roulette;
    double reduction, delta, init_width, min_width, tol, bump;
    unsigned long long seed;
    int counter;
    long long moved;
    int failed;
} CiJob;

static void *ci_worker(void *arg) {
    CiJob *J = arg;
    double *X = J->X, *WIDTH = J->WIDTH;
    const double *BASIS = J->BASIS, *FREE = J->FREE, *PLANE = J->PLANE;
    const conn_t *HEX = J->HEX;
    const long long *ROT = J->ROT, *INC = J->INC, *CNT = J->CNT, *ROW = J->ROW, *KIND = J->KIND, *NODES = J->NODES;
    Cells *cells = J->cells;
    Py_ssize_t K = J->K;
    int C = J->C, t = J->t, T = J->T, n_roulette = J->n_roulette;
    double reduction = J->reduction, delta = J->delta, init_width = J->init_width, min_width = J->min_width,
           tol = J->tol, bump = J->bump;
    Elem *E = malloc(sizeof(Elem) * (K ? K : 1));
    int S = C * t; /* the trials of one learning attempt, all candidates' */
    double *work = malloc(sizeof(double) * ((size_t)C * 10 + (size_t)S * 4));
    long long *iwork = malloc(sizeof(long long) * ((size_t)C * 3 + (size_t)S));
    Py_ssize_t NPmax = poly_width(K);
    double *P = malloc(sizeof(double) * POLY_ROWS * (size_t)(NPmax ? NPmax : POLY_LANES));
    double *shrink = malloc(sizeof(double) * (size_t)(T ? T : 1)); /* reduction^(a + 1) of attempt a */
    if (!E || !work || !iwork || !P || !shrink) {
        J->failed = 1;
        free(E); free(work); free(iwork); free(P); free(shrink);
        return NULL;
    }
    for (int a = 0; a < T; a++) shrink[a] = pow(reduction, (double)(a + 1));
    double *cand = work, *centre = work + 3 * C, *fc = work + 6 * C, *cum = work + 7 * C;
    double *ys = work + 10 * C, *fs = work + 10 * C + 3 * S; /* trials (3 x S) and their local objectives */
    long long *ch = iwork, *chint = iwork + C, *follow = iwork + 2 * C, *hs = iwork + 3 * C;
    for (Py_ssize_t m = J->lo; m < J->hi; m++) {
        Draws rng; /* each node its own stream: the same result on any number of threads */
        unsigned long long sm = J->seed ^ (0x9e3779b97f4a7c15ULL * (unsigned long long)(m + 1));
        for (int i = 0; i < 4; i++) rng.rng.s[i] = splitmix(&sm);
        rng.counter = J->counter;
        rng.h = mix32((unsigned int)J->seed, (unsigned int)NODES[m]); /* the visit's word, then the node */
        double *xv = X + 3 * NODES[m], x0[3] = {xv[0], xv[1], xv[2]}, w0 = WIDTH[NODES[m]], h = 0.0;
        const double *basis = BASIS + 9 * m, *fr = FREE + 3 * m, *pl = PLANE + 7 * m;
        long long kd = KIND[m];
        Cells *cl = kd ? &cells[kd - 1] : NULL;
        const int *crow = cl ? cl->cand + ROW[m] * cl->K : NULL;
        Py_ssize_t cnt = CNT[m];
        for (Py_ssize_t k = 0; k < cnt; k++) {
            elem_setup(X, HEX, ROT, INC[m * K + k], &E[k]);
            for (int j = 0; j < 3; j++) {
                const double *P = j == 0 ? E[k].P1 : (j == 1 ? E[k].P3 : E[k].P4);
                double d2 = 0.0;
                for (int d = 0; d < 3; d++) d2 += (P[d] - x0[d]) * (P[d] - x0[d]);
                h += sqrt(d2);
            }
        }
        h /= 3.0 * (double)(cnt > 0 ? cnt : 1);
        double ncorner = (double)(4 * cnt > 0 ? 4 * cnt : 1), f0;
        Py_ssize_t NP = poly_width(cnt);
        poly_setup(E, cnt, x0, P, NP);
        poly_sums(P, NP, x0, x0, 1, &f0);
        f0 = f0 / ncorner - 1.0;
        long long hint0 = cl ? cl->hint[ROW[m]] : -1;
        for (int c = 0; c < C; c++) {
            for (int d = 0; d < 3; d++) cand[3 * c + d] = x0[d];
            fc[c] = f0;
            ch[c] = hint0;
        }
        for (int a = 0; a < T; a++) {
            if (a < n_roulette) { /* roulette on 1 / (g + delta): an inverted candidate (inf) has probability 0 */
                double total = 0.0;
                for (int c = 0; c < C; c++) cum[c] = (total += 1.0 / (fc[c] + delta));
                for (int c = 0; c < C; c++) {
                    double draw = uniform(&rng, a, 0, c) * total;
                    int j = 0;
                    while (j < C && draw >= cum[j]) j++;
                    follow[c] = j < C ? j : C - 1;
                }
            } else {
                int best = 0;
                for (int c = 1; c < C; c++)
                    if (fc[c] < fc[best]) best = c;
                for (int c = 0; c < C; c++) follow[c] = best;
            }
            for (int c = 0; c < C; c++) {
                for (int d = 0; d < 3; d++) centre[3 * c + d] = cand[3 * follow[c] + d];
                chint[c] = ch[follow[c]];
            }
            double w = w0 * shrink[a];
            /* every candidate's t trials first (the random numbers drawn in the order candidate, trial), then
             * their local objectives at once (poly_sums, the corners vectorised) */
            for (int c = 0; c < C; c++)
                for (int j = 0; j < t; j++) {
                    double u[3], y[3];
                    long long hy = chint[c];
                    for (int d = 0; d < 3; d++) u[d] = (uniform(&rng, a, 1, (c * t + j) * 3 + d) - 0.5) * w * fr[d];
                    for (int i = 0; i < 3; i++)
                        y[i] = centre[3 * c + i] + basis[3 * i] * u[0] + basis[3 * i + 1] * u[1] + basis[3 * i + 2] * u[2];
                    int flat = 0;
                    if (kd == 1 && pl[6] > 0.0) { /* inside its planar disk: the plane projection is exact */
                        double q = (y[0] - pl[0]) * pl[3] + (y[1] - pl[1]) * pl[4] + (y[2] - pl[2]) * pl[5], r2 = 0.0,
                               f[3];
                        for (int d = 0; d < 3; d++) {
                            f[d] = y[d] - q * pl[3 + d];
                            r2 += (f[d] - pl[d]) * (f[d] - pl[d]);
                        }
                        if ((flat = r2 < (0.999 * pl[6]) * (0.999 * pl[6])))
                            for (int d = 0; d < 3; d++) y[d] = f[d];
                    }
                    if (kd && !flat)
                        project_one(y, crow, cl->K, &hy, cl->table, cl->nc, cl->spheres, cl->faces, (int)kd - 1, tol, bump);
                    int s = c * t + j;
                    for (int d = 0; d < 3; d++) ys[d * S + s] = y[d];
                    hs[s] = hy;
                }
            poly_sums(P, NP, x0, ys, S, fs);
            for (int s = 0; s < S; s++) fs[s] = fs[s] / ncorner - 1.0;
            for (int c = 0; c < C; c++) {
                double fb = INFINITY, yb[3] = {0.0, 0.0, 0.0};
                long long hb = chint[c];
                for (int j = 0; j < t; j++) {
                    int s = c * t + j;
                    if (fs[s] < fb) {
                        fb = fs[s];
                        hb = hs[s];
                        for (int d = 0; d < 3; d++) yb[d] = ys[d * S + s];
                    }
                }
                if (fb < fc[c]) {
                    fc[c] = fb;
                    ch[c] = hb;
                    for (int d = 0; d < 3; d++) cand[3 * c + d] = yb[d];
                }
            }
        }
        int best = 0;
        for (int c = 1; c < C; c++)
            if (fc[c] < fc[best]) best = c;
        int accept = fc[best] < f0 && isfinite(fc[best]);
        double move2 = 0.0;
        if (accept) {
            for (int d = 0; d < 3; d++) {
                move2 += (cand[3 * best + d] - x0[d]) * (cand[3 * best + d] - x0[d]);
                xv[d] = cand[3 * best + d];
            }
            if (cl) cl->hint[ROW[m]] = ch[best];
        }
        double wn = accept ? 4.0 * sqrt(move2) : 0.5 * w0, lo = min_width * h, hi = init_width * h;
        WIDTH[NODES[m]] = wn < lo ? lo : (wn > hi ? hi : wn);
        J->moved += accept;
    }
    free(E); free(work); free(iwork); free(P); free(shrink);
    return NULL;
}

static PyObject *ci_visit(PyObject *self, PyObject *args) {
    PyObject *o[20], *ret = NULL;
    int C, t, T, n_roulette;
    double reduction, delta, init_width, min_width, tol, bump;
    unsigned long long seed;
    int nthreads = 1, counter = 0;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOOOOOiiiiddddddK|ii", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &o[12], &o[13], &o[14], &o[15], &o[16], &o[17],
                          &o[18], &o[19], &C, &t, &T, &n_roulette, &reduction, &delta, &init_width, &min_width, &tol,
                          &bump, &seed, &nthreads, &counter))
        return NULL;
    static const Arg spec[20] = {{"x", "d", 1}, {"width", "d", 1}, {"nodes", "qlq"}, {"inc", "qlq"}, {"count", "qlq"},
                                 {"basis", "d"}, {"free", "d"}, {"plane", "d"}, {"row", "qlq"}, {"kind", "qlq"},
                                 {"hint_s", "qlq", 1}, {"hint_e", "qlq", 1}, {"cand_s", "i"}, {"table_s", "d"},
                                 {"spheres_s", "d"}, {"cand_e", "i"}, {"table_e", "d"}, {"spheres_e", "d"},
                                 {"hexes", "i"}, {"rot", "qlq"}};
    Buf B[20] = {{{0}}};
    if (acquire_args(B, o, spec, 20) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, M = B[2].view.len / 8, K = M ? B[3].view.len / 8 / M : 0,
               N = B[18].view.len / 32;
    Cells cells[2];
    for (int k = 0; k < 2; k++) {
        Buf *c = &B[12 + 3 * k];
        cells[k].rows = c->view.ndim == 2 ? c->view.shape[0] : 0; /* may hold padding rows beyond the hints' */
        cells[k].K = c->view.ndim == 2 ? c->view.shape[1] : 0;
        cells[k].nc = B[13 + 3 * k].view.len / 8 / (k == 0 ? TRI_ROWS : SEG_ROWS);
        cells[k].cand = c->view.buf;
        cells[k].table = B[13 + 3 * k].view.buf;
        cells[k].spheres = B[14 + 3 * k].view.buf;
        cells[k].faces = B[14 + 3 * k].view.len == cells[k].nc * 32 ? NULL : cells[k].spheres + 4 * cells[k].nc;
        cells[k].hint = B[10 + k].view.buf;
        if (c->view.len != cells[k].rows * cells[k].K * 4 || B[10 + k].view.len / 8 > cells[k].rows ||
            (B[14 + 3 * k].view.len != cells[k].nc * 32 && B[14 + 3 * k].view.len != face_spheres(cells[k].nc, k) * 32) ||
            check_indices_of(cells[k].cand, 4, cells[k].rows * cells[k].K, cells[k].nc, "ci_visit") < 0) {
            if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "ci_visit: the cell tables disagree");
            goto done;
        }
    }
    if (B[0].view.len != n * 24 || B[1].view.len != n * 8 || B[3].view.len != M * K * 8 || B[4].view.len != M * 8 ||
        B[5].view.len != M * 72 || B[6].view.len != M * 24 || B[7].view.len != M * 56 || B[8].view.len != M * 8 ||
        B[9].view.len != M * 8 || B[18].view.len != N * 32 || B[19].view.len != 512 || C < 1 || t < 1 || T < 0) {
        PyErr_SetString(PyExc_ValueError, "ci_visit: shapes disagree");
        goto done;
    }
    const long long *NODES = B[2].view.buf, *INC = B[3].view.buf, *CNT = B[4].view.buf, *ROW = B[8].view.buf,
                    *KIND = B[9].view.buf, *ROT = B[19].view.buf;
    const conn_t *HEX = B[18].view.buf;
    if (check_indices(NODES, M, n, "ci_visit") < 0 || check_stars(HEX, N, n, ROT, INC, CNT, M, K, "ci_visit") < 0)
        goto done;
    for (Py_ssize_t m = 0; m < M; m++) {
        long long kd = KIND[m];
        if (kd < 0 || kd > 2 ||
            (kd > 0 && (ROW[m] < 0 || ROW[m] >= B[9 + kd].view.len / 8 || cells[kd - 1].K < 1 ||
                        cells[kd - 1].hint[ROW[m]] >= cells[kd - 1].K))) {
            PyErr_SetString(PyExc_IndexError, "ci_visit: kind, row or hint out of range");
            goto done;
        }
    }
    int nt = threads_for(M, nthreads, 32); /* a thread per 32 nodes at least */
    CiJob jobs[MAX_THREADS];
    for (int j = 0; j < nt; j++)
        jobs[j] = (CiJob){B[0].view.buf, B[1].view.buf, B[5].view.buf, B[6].view.buf, B[7].view.buf, NODES, HEX, ROT,
                          INC, CNT, ROW, KIND, cells, K, M * j / nt, M * (j + 1) / nt, C, t, T, n_roulette, reduction, delta,
                          init_width, min_width, tol, bump, seed, counter, 0, 0};
    if (run_jobs(jobs, sizeof(CiJob), nt, ci_worker, NULL, 0, 0, NULL) < 0) goto done;
    long long moved = 0;
    for (int j = 0; j < nt; j++) {
        if (jobs[j].failed) {
            PyErr_NoMemory();
            goto done;
        }
        moved += jobs[j].moved;
    }
    ret = PyLong_FromLongLong(moved);
done:
    release(B, 20);
    return ret;
}

/* ------------------------------------------------------------------------------------ the free coordinates
 * The linear map B of jaxci.optim.parametrisation.lift_points (free coordinates laid out as 3 per interior node,
 * 2 per surface node along its tangent basis, 1 per edge node along its tangent), its transpose, the flat-region
 * test and the projection's derivative of jaxci.optim.host.HostObjective: each one pass over the nodes, where
 * numpy's fancy indexing took ~1 ms of a 3 ms L-BFGS step on 2,000 hexahedra. The layout arrays: interior (ni,),
 * surface (ns,), basis (ns, 2, 3), edge (ne,), tangent (ne, 3). */
typedef struct {
    const int *I, *S, *E; /* int32: the constraints' own arrays (an int64 copy was 1.7 MB at 216,000 hexahedra) */
    const double *SB, *ET;
    Py_ssize_t ni, ns, ne;
} Layout;

/* The layout from buffers B[0..4] (interior, surface, basis, edge, tangent), its indices checked against n. */
static int get_layout(Buf *B, Py_ssize_t n, Layout *L, const char *fn) {
    L->ni = B[0].view.len / 4;
    L->ns = B[1].view.len / 4;
    L->ne = B[3].view.len / 4;
    if (B[2].view.len != L->ns * 48 || B[4].view.len != L->ne * 24) {
        PyErr_Format(PyExc_ValueError, "%s: layout shapes disagree", fn);
        return -1;
    }
    L->I = B[0].view.buf;
    L->S = B[1].view.buf;
    L->SB = B[2].view.buf;
    L->E = B[3].view.buf;
    L->ET = B[4].view.buf;
    if (check_indices_of(L->I, 4, L->ni, n, fn) < 0 || check_indices_of(L->S, 4, L->ns, n, fn) < 0 ||
        check_indices_of(L->E, 4, L->ne, n, fn) < 0)
        return -1;
    return 0;
}

/* The layout's arguments in an Arg table (get_layout's B[0..4]). */
#define LAYOUT_ARGS {"interior", "i"}, {"surface", "i"}, {"basis", "d"}, {"edge", "i"}, {"tangent", "d"}

/* lift(x0 (n,3) f8, scale (m,) f8, v (m,) f8, interior, surface, basis, edge, tangent, x (n,3) f8 out[, d (m,)
 * f8, alpha]) -> int: x = x0 + B (scale * v); with d, of the trial point d * alpha + v instead (each entry the
 * product, then the sum, as numpy's ``d * alpha`` then ``+= v``; no trial vector made), and returns how many of
 * its entries differ from v's (0 without d). */
static PyObject *lift(PyObject *self, PyObject *args) {
    PyObject *o[10] = {NULL}, *ret = NULL;
    double alpha = 1.0;
    o[9] = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOOOOOO|Od", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8],
                          &o[9], &alpha))
        return NULL;
    static const Arg spec[10] = {{"x0", "d"}, {"scale", "d"}, {"v", "d"}, LAYOUT_ARGS, {"x", "d", 1},
                                 {"d", "d", 0, 1}};
    Buf B[10] = {{{0}}};
    Layout L;
    if (acquire_args(B, o, spec, 10) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8;
    if (get_layout(B + 3, n, &L, "lift") < 0) goto done;
    if (B[8].view.len != B[0].view.len || B[2].view.len != B[1].view.len || m != 3 * L.ni + 2 * L.ns + L.ne ||
        (B[9].held && B[9].view.len != B[1].view.len)) {
        PyErr_SetString(PyExc_ValueError, "lift: shapes disagree");
        goto done;
    }
    const double *X0 = B[0].view.buf, *SC = B[1].view.buf, *V = B[2].view.buf;
    const double *D = B[9].held ? B[9].view.buf : NULL;
    double *X = B[8].view.buf;
    memcpy(X, X0, (size_t)B[0].view.len);  /* the fixed nodes' */
    const Py_ssize_t os = 3 * L.ni, oe = os + 2 * L.ns;
    for (Py_ssize_t k = 0; k < L.ni; k++)
        lift_interior_at(X0 + 3 * L.I[k], SC, V, D, alpha, 3 * k, X + 3 * L.I[k]);
    for (Py_ssize_t k = 0; k < L.ns; k++)
        lift_surface_at(X0 + 3 * L.S[k], SC, V, D, alpha, os + 2 * k, L.SB + 6 * k, X + 3 * L.S[k]);
    for (Py_ssize_t k = 0; k < L.ne; k++)
        lift_edge_at(X0 + 3 * L.E[k], SC, V, D, alpha, oe + k, L.ET + 3 * k, X + 3 * L.E[k]);
    ret = PyLong_FromLongLong(trial_moved(V, D, alpha, m));
done:
    release(B, 10);
    return ret;
}

/* lift_t(g (n,3) f8, scale (m,) f8, interior, surface, basis, edge, tangent, out (m,) f8) -> None: out =
 * scale * B^T g (jaxci.optim.parametrisation.lift_transpose_np). */
static PyObject *lift_t(PyObject *self, PyObject *args) {
    PyObject *o[8], *ret = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7])) return NULL;
    static const Arg spec[8] = {{"g", "d"}, {"scale", "d"}, LAYOUT_ARGS, {"out", "d", 1}};
    Buf B[8] = {{{0}}};
    Layout L;
    double *tail = NULL; /* the boundary nodes' entries aside (in place) */
    if (acquire_args(B, o, spec, 8) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8;
    if (get_layout(B + 2, n, &L, "lift_t") < 0) goto done;
    if (B[7].view.len != B[1].view.len || m != 3 * L.ni + 2 * L.ns + L.ne) {
        PyErr_SetString(PyExc_ValueError, "lift_t: shapes disagree");
        goto done;
    }
    const double *G = B[0].view.buf, *SC = B[1].view.buf;
    double *out = B[7].view.buf;
    /* out over g's own buffer (its first m entries: `jaxci.native.lift_t` with inplace): the boundary nodes'
     * entries first, aside, then the interior nodes' in ascending order, each written at or before the entry it
     * reads (interior[k] >= k), then the boundary's after them */
    int inplace = (const double *)out == G;
    if (inplace) {
        for (Py_ssize_t k = 1; k < L.ni; k++)
            if (L.I[k] <= L.I[k - 1]) {
                PyErr_SetString(PyExc_ValueError, "lift_t: in place needs the interior nodes in ascending order");
                goto done;
            }
        if (!(tail = malloc((size_t)(2 * L.ns + L.ne + 1) * sizeof(double)))) {
            PyErr_NoMemory();
            goto done;
        }
    } else if ((const char *)out < (const char *)G + B[0].view.len && (const char *)G < (const char *)(out + m)) {
        PyErr_SetString(PyExc_ValueError, "lift_t: out overlaps g other than at its start");
        goto done;
    }
    double *os = inplace ? tail : out + 3 * L.ni;
    const double *SCs = SC + 3 * L.ni;
    for (Py_ssize_t k = 0; k < L.ns; k++) {
        const double *g = G + 3 * L.S[k], *b = L.SB + 6 * k;
        /* summed in the order numpy's einsum took here (x + z, then y): the same gradient as the numpy path */
        os[2 * k] = SCs[2 * k] * ((g[0] * b[0] + g[2] * b[2]) + g[1] * b[1]);
        os[2 * k + 1] = SCs[2 * k + 1] * ((g[0] * b[3] + g[2] * b[5]) + g[1] * b[4]);
    }
    double *oe = os + 2 * L.ns;
    const double *SCe = SCs + 2 * L.ns;
    for (Py_ssize_t k = 0; k < L.ne; k++) {
        const double *g = G + 3 * L.E[k], *t = L.ET + 3 * k;
        oe[k] = SCe[k] * (g[0] * t[0] + g[1] * t[1] + g[2] * t[2]);
    }
    for (Py_ssize_t k = 0; k < L.ni; k++)
        for (int d = 0; d < 3; d++) out[3 * k + d] = SC[3 * k + d] * G[3 * L.I[k] + d];
    if (inplace) memcpy(out + 3 * L.ni, tail, (size_t)(2 * L.ns + L.ne) * sizeof(double));
    ret = Py_NewRef(Py_None);
done:
    free(tail);
    release(B, 8);
    return ret;
}

/* The Lifted source of buffers B[0..5] (x0 (n,3) f8, scale (m,) f8, v (m,) f8, d (m,) f8 or None, slot (n,) i4,
 * basis (ns,2,3) f8, tangent (ne,3) f8: B[6]) and alpha, every slot checked. */
static int get_lifted(Buf *B, double alpha, Lifted *L, Py_ssize_t *n_out, const char *fn) {
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8, ns = B[5].view.len / 48, ne = B[6].view.len / 24;
    Py_ssize_t ni3 = m - 2 * ns - ne;
    if (B[0].view.len != n * 24 || B[2].view.len != B[1].view.len || (B[3].held && B[3].view.len != B[1].view.len) ||
        B[4].view.len != n * 4 || B[5].view.len != ns * 48 || B[6].view.len != ne * 24 || ni3 < 0 || ni3 % 3) {
        PyErr_Format(PyExc_ValueError, "%s: shapes disagree", fn);
        return -1;
    }
    *L = (Lifted){B[0].view.buf, B[1].view.buf, B[2].view.buf, B[3].held ? B[3].view.buf : NULL, B[5].view.buf,
                  B[6].view.buf, B[4].view.buf, alpha, ni3, ni3 + 2 * ns};
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t t = L->slot[i];
        if (!(t == -1 || (t >= 0 && t < L->os && t % 3 == 0) || (t >= L->os && t < L->oe && (t - L->os) % 2 == 0) ||
              (t >= L->oe && t < m))) {
            PyErr_Format(PyExc_IndexError, "%s: slot %zd of node %zd out of range", fn, t, i);
            return -1;
        }
    }
    *n_out = n;
    return 0;
}

/* The arguments o[0..8] of an entry point on lifted points (x0, scale, v, d or None, slot, basis, tangent, then the
 * two of `tail`) acquired into B[0..8], and their Lifted source: 0, else -1 with the exception set. */
static int lifted_call(PyObject **o, Buf *B, const Arg *tail, double alpha, Lifted *L, Py_ssize_t *n,
                       const char *fn) {
    const Arg spec[9] = {{"x0", "d"}, {"scale", "d"}, {"v", "d"}, {"d", "d", 0, 1}, {"slot", "i"}, {"basis", "d"},
                         {"tangent", "d"}, tail[0], tail[1]};
    return acquire_args(B, o, spec, 9) < 0 || get_lifted(B, alpha, L, n, fn) < 0 ? -1 : 0;
}

/* lift_nodes(x0, scale, v, d or None, alpha, slot, basis, tangent, nodes (k,) i8, out (k,3) f8) -> int: out[j] =
 * the lifted coordinates of node nodes[j] (of the trial point d * alpha + v with d: lift's numbers); returns how
 * many entries of the trial point differ from v's (0 without d). */
static PyObject *lift_nodes(PyObject *self, PyObject *args) {
    PyObject *o[9], *ret = NULL;
    double alpha;
    if (!PyArg_ParseTuple(args, "OOOOdOOOOO", &o[0], &o[1], &o[2], &o[3], &alpha, &o[4], &o[5], &o[6], &o[7], &o[8]))
        return NULL;
    static const Arg tail[2] = {{"nodes", "qlq"}, {"out", "d", 1}};
    Buf B[9] = {{{0}}};
    Lifted L;
    Py_ssize_t n;
    if (lifted_call(o, B, tail, alpha, &L, &n, "lift_nodes") < 0) goto done;
    Py_ssize_t k = B[7].view.len / 8, m = B[1].view.len / 8;
    if (B[8].view.len != k * 24) {
        PyErr_SetString(PyExc_ValueError, "lift_nodes: shapes disagree");
        goto done;
    }
    const long long *N = B[7].view.buf;
    if (check_indices(N, k, n, "lift_nodes") < 0) goto done;
    double *out = B[8].view.buf;
    for (Py_ssize_t j = 0; j < k; j++) lifted_xyz(&L, N[j], out + 3 * j);
    ret = PyLong_FromLongLong(trial_moved(L.V, L.D, alpha, m));
done:
    release(B, 9);
    return ret;
}

/* hex_condition_lifted(x0, scale, v, d or None, alpha, slot, basis, tangent, hexes (N,8) i4, weight, grad (n,3) f8,
 * nthreads) -> hex_condition's (sum, max term, inverted corners) with its gradient, of the points lift (lift's
 * trial point with d) would make, each read where a corner needs it: no (n, 3) array of them (5 MB at 216,000
 * hexahedra, beside the gradient's, while the kernel runs). */
static PyObject *hex_condition_lifted(PyObject *self, PyObject *args) {
    PyObject *o[9], *ret = NULL;
    double alpha, weight;
    int nthreads = 1;
    if (!PyArg_ParseTuple(args, "OOOOdOOOOdO|i", &o[0], &o[1], &o[2], &o[3], &alpha, &o[4], &o[5], &o[6], &o[7],
                          &weight, &o[8], &nthreads))
        return NULL;
    static const Arg tail[2] = {{"hexes", "i"}, {"grad", "d", 1}};
    Buf B[9] = {{{0}}};
    Lifted L;
    Py_ssize_t n;
    if (lifted_call(o, B, tail, alpha, &L, &n, "hex_condition_lifted") < 0) goto done;
    Py_ssize_t N = B[7].view.len / 32;
    if (B[7].view.len != N * 32 || B[8].view.len != n * 24) {
        PyErr_SetString(PyExc_ValueError, "hex_condition_lifted: shapes disagree (hexes (N, 8), grad (n, 3))");
        goto done;
    }
    if (check_conn(B[7].view.buf, 8 * N, n, "hex_condition_lifted") < 0) goto done;
    HexJob jobs[MAX_THREADS];
    int nt = threads_for(N, nthreads, MIN_PER_THREAD);
    for (int t = 0; t < nt; t++)
        jobs[t] = (HexJob){{0.0, 0.0, 0}, NULL, NULL, B[7].view.buf, NULL, NULL, N, N * t / nt, N * (t + 1) / nt,
                           weight, NULL, 0.0, 0.0, 0, &L};
    Nodes nd = {B[7].view.buf, N, 8, 1, 8, 0};
    if (run_jobs(jobs, sizeof(HexJob), nt, hex_worker, B[8].view.buf, 3 * n, offsetof(HexJob, G), &nd) < 0) goto done;
    ret = total_sums(jobs, sizeof(HexJob), nt);
done:
    release(B, 9);
    return ret;
}

/* flat_keep(x (n,3) f8, nodes (m,) i8, origin (m,3) f8, r2 (m,) f8, keep (n,) bool out) -> int: keep[nodes[k]] =
 * whether node nodes[k] lies strictly inside the ball of squared radius r2[k] around origin[k] (its flat region);
 * returns how many do not. */
static PyObject *flat_keep(PyObject *self, PyObject *args) {
    PyObject *o[5], *ret = NULL;
    if (!PyArg_ParseTuple(args, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4])) return NULL;
    static const Arg spec[5] = {{"x", "d"}, {"nodes", "qlq"}, {"origin", "d"}, {"r2", "d"}, {"keep", "?", 1}};
    Buf B[5] = {{{0}}};
    if (acquire_args(B, o, spec, 5) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8;
    if (B[2].view.len != 3 * B[1].view.len || B[3].view.len != B[1].view.len || B[4].view.len != n) {
        PyErr_SetString(PyExc_ValueError, "flat_keep: shapes disagree");
        goto done;
    }
    const long long *N = B[1].view.buf;
    if (check_indices(N, m, n, "flat_keep") < 0) goto done;
    const double *X = B[0].view.buf, *O = B[2].view.buf, *R2 = B[3].view.buf;
    char *keep = B[4].view.buf;
    long long outside = 0;
    for (Py_ssize_t k = 0; k < m; k++) {
        const double *x = X + 3 * N[k], *c = O + 3 * k;
        double d0 = x[0] - c[0], d1 = x[1] - c[1], d2 = x[2] - c[2];
        int in = d0 * d0 + d1 * d1 + d2 * d2 < R2[k];
        keep[N[k]] = (char)in;
        outside += !in;
    }
    ret = PyLong_FromLongLong(outside);
done:
    release(B, 5);
    return ret;
}

/* pullback(g (n,3) f8 in place, nodes (m,) i8, hint (m,) i8, keep (n,) bool or None, cand (m,K) i4, table f8,
 * kind) -> None: at node nodes[i] with hint[i] >= 0 and not kept, g minus its component along its triangle's unit
 * normal (kind 0; table columns 9-11) or g's component along its segment (kind 1; columns 3-5): the derivative of the
 * projection onto a plane or a line (jaxci.geometry.near.NearProjector.pullback). */
static PyObject *pullback(PyObject *self, PyObject *args) {
    PyObject *o[6], *ret = NULL;
    int kind;
    if (!PyArg_ParseTuple(args, "OOOOOOi", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &kind)) return NULL;
    static const Arg spec[6] = {{"g", "d", 1}, {"nodes", "qlq"}, {"hint", "qlq"}, {"keep", "?", 0, 1}, {"cand", "i"},
                                {"table", "d"}};
    Buf B[6] = {{{0}}};
    if (acquire_args(B, o, spec, 6) < 0) goto done;
    Py_ssize_t n = B[0].view.len / 24, m = B[1].view.len / 8, rows = kind == 0 ? TRI_ROWS : SEG_ROWS;
    Py_ssize_t nc = B[5].view.len / 8 / rows, K = B[4].view.ndim == 2 ? B[4].view.shape[1] : 0;
    if ((kind != 0 && kind != 1) || B[2].view.len != B[1].view.len || (B[3].held && B[3].view.len != n) ||
        B[5].view.len != nc * rows * 8 || (m && (K < 1 || B[4].view.len < m * K * 4))) {
        PyErr_SetString(PyExc_ValueError, "pullback: shapes disagree");
        goto done;
    }
    const long long *N = B[1].view.buf, *H = B[2].view.buf;
    const int *CA = B[4].view.buf;
    if (check_indices(N, m, n, "pullback") < 0) goto done;
    const char *keep = B[3].held ? B[3].view.buf : NULL;
    const double *T = B[5].view.buf;
    double *G = B[0].view.buf;
    int row = kind == 0 ? TN : SD;
    for (Py_ssize_t i = 0; i < m; i++) {
        if (H[i] < 0 || (keep && keep[N[i]])) continue;
        if (H[i] >= K || CA[i * K + H[i]] < 0 || CA[i * K + H[i]] >= nc) {
            PyErr_SetString(PyExc_IndexError, "pullback: hint out of range");
            goto done;
        }
        Py_ssize_t j = CA[i * K + H[i]];
        double d[3] = {T[j * rows + row], T[j * rows + row + 1], T[j * rows + row + 2]};
        double norm = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        if (norm < 1e-300) norm = 1e-300;
        for (int k = 0; k < 3; k++) d[k] /= norm;
        double *g = G + 3 * N[i], a = g[0] * d[0] + g[1] * d[1] + g[2] * d[2];
        for (int k = 0; k < 3; k++) g[k] = kind == 0 ? g[k] - a * d[k] : a * d[k];
    }
    ret = Py_NewRef(Py_None);
done:
    release(B, 6);
    return ret;
}

/* ------------------------------------------------------------------------------------------ colouring
 * greedy_colour(cells (N,k) i4, n, colour (n,) i8) -> None: the first-fit colouring of the nodes in index order
 * (jaxci.geometry.topology.colour_nodes): node v takes the smallest colour that no lower-numbered node sharing a
 * cell with it has. The same colours as the numpy rounds (Jones-Plassmann with the index as priority), one pass. */
static PyObject *greedy_colour(PyObject *self, PyObject *args) {
    static const Arg spec[2] = {{"cells", "i"}, {"colour", "qlq", 1}};
    PyObject *o[2], *ret = NULL;
    Py_ssize_t n, k;
    if (!PyArg_ParseTuple(args, "OnnO", &o[0], &n, &k, &o[1])) return NULL;
    Buf B[2] = {{{0}}};
    long long *start = NULL, *mark = NULL;
    int32_t *inc = NULL; /* the cells around each node (fewer than 2^31 cells) */
    if (acquire_args(B, o, spec, 2) < 0) goto done;
    Py_ssize_t N = k > 0 ? B[0].view.len / 4 / k : 0;
    if (k < 1 || n < 0 || B[0].view.len != N * k * 4 || B[1].view.len != n * 8) {
        PyErr_SetString(PyExc_ValueError, "greedy_colour: shapes disagree (cells (N, k), colour (n,))");
        goto done;
    }
    if (N >= INT32_MAX) {
        PyErr_SetString(PyExc_ValueError, "greedy_colour: 2^31 - 1 cells or more (its incidences are int32)");
        goto done;
    }
    const conn_t *CELL = B[0].view.buf;
    long long *COL = B[1].view.buf;
    if (check_conn(CELL, N * k, n, "greedy_colour") < 0) goto done;
    start = calloc((size_t)n + 1, sizeof(long long));
    inc = malloc(sizeof(int32_t) * (size_t)(N * k > 0 ? N * k : 1));
    mark = malloc(sizeof(long long) * (size_t)(n + 1));
    if (!start || !inc || !mark) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < N * k; i++) start[CELL[i] + 1]++;
    for (Py_ssize_t v = 0; v < n; v++) start[v + 1] += start[v];
    for (Py_ssize_t i = 0; i < N * k; i++) inc[start[CELL[i]]++] = (int32_t)(i / k); /* start[v] becomes v's end */
    for (Py_ssize_t v = n; v > 0; v--) start[v] = start[v - 1];
    start[0] = 0;
    for (Py_ssize_t c = 0; c <= n; c++) mark[c] = -1;
    for (Py_ssize_t v = 0; v < n; v++) {
        for (long long j = start[v]; j < start[v + 1]; j++) {
            const conn_t *cell = CELL + (Py_ssize_t)inc[j] * k;
            for (Py_ssize_t q = 0; q < k; q++)
                if (cell[q] < v) mark[COL[cell[q]]] = v;
        }
        long long c = 0;
        while (mark[c] == v) c++;
        COL[v] = c;
    }
    Py_END_ALLOW_THREADS
    ret = Py_NewRef(Py_None);
done:
    free(start); free(inc); free(mark);
    release(B, 2);
    return ret;
}

static PyMethodDef methods[] = {
    {"hex_condition", hex_condition, METH_VARARGS, "F terms of hexahedra, their sum, max and gradient"},
    {"ffi_handler", ffi_handler, METH_NOARGS,
     "the XLA FFI handler of hex_condition, as a PyCapsule (None: built without XLA's FFI header)"},
    {"ffi_api_version", ffi_api_version, METH_NOARGS,
     "(major, minor) of the XLA FFI header the handler was built against (None: no handler)"},
    {"hex_determinants", hex_determinants, METH_VARARGS, "det A_i of every corner of every hexahedron"},
    {"corner_condition", corner_condition, METH_VARARGS, "terms of a corner table of any cell type and their gradient"},
    {"near_project", near_project, METH_VARARGS, "boundary nodes to their nearest candidate triangle or segment"},
    {"lbfgs_direction", lbfgs_direction, METH_VARARGS, "the L-BFGS two-loop recursion"},
    {"half_dots", half_dots, METH_VARARGS, "the curvature sums of a float16 L-BFGS pair"},
    {"coarse_apply", py_coarse_apply, METH_VARARGS, "the two-level preconditioner of jaxci.optim.coarse"},
    {"untangle_energy", untangle_energy, METH_VARARGS, "the untangling energy of hexahedra and its gradient"},
    {"local_sums", local_sums, METH_VARARGS, "local objective sums of trial positions of nodes in their stars"},
    {"ci_visit", ci_visit, METH_VARARGS, "one cohort run of local CI for every node of one colour"},
    {"lift", lift, METH_VARARGS, "node coordinates from scaled free coordinates"},
    {"lift_nodes", lift_nodes, METH_VARARGS, "some nodes' coordinates from scaled free coordinates"},
    {"hex_condition_lifted", hex_condition_lifted, METH_VARARGS, "hex_condition of points lifted as read"},
    {"lift_t", lift_t, METH_VARARGS, "a node gradient taken to the scaled free coordinates"},
    {"flat_keep", flat_keep, METH_VARARGS, "which boundary nodes lie inside their flat regions"},
    {"pullback", pullback, METH_VARARGS, "a node gradient through the projection onto planes or lines"},
    {"greedy_colour", greedy_colour, METH_VARARGS, "first-fit colouring of the nodes in index order"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ckernels", "jaxci's fused C kernels", -1, methods};

PyMODINIT_FUNC PyInit__ckernels(void) {
    for (int h = 0; h < 65536; h++) HALF[h] = half_value((uint16_t)h);
    PyObject *m = PyModule_Create(&module);
    /* the interface's version (jaxci.cells.KERNELS_ABI): a build of older sources is refused, not run */
    if (m != NULL && PyModule_AddIntConstant(m, "ABI", 6) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
