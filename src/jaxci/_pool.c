/* jaxci._ckernels' worker threads: kept between kernel calls, so that a call's parts start in microseconds.
 *
 * A kernel call of jaxci._ckernels splits its elements (or nodes) among up to MAX_THREADS threads, each over
 * its own fixed range (run_jobs_nogil). Creating those threads for every call, as it did, cost far more than a
 * thread's creation alone on the 2-core VM this was measured on (AMD EPYC, 2026-12-01): the penalty kernel of
 * the worst-element polish over 4,096 hexahedra took 624 us on two threads against 615 us on one, and over
 * 6,980 hexahedra 845 against 1,051 us: about 300 us a call went to starting the second thread on a CPU that was
 * idle and to mapping, zeroing and unmapping its gradient buffer. Here the threads are made once (on the first
 * call that wants them) and wait for the next call: first spinning for up to SPIN_NS (the L-BFGS loops call a
 * kernel every few hundred microseconds), then asleep on a condition variable, so an idle process uses no CPU
 * after that. Each keeps its gradient buffer between calls (up to BUF_MAX doubles; a larger one is allocated for
 * the call, as before) and zeroes it itself.
 *
 * The ranges, the sums and their order are the caller's, as before: the results are the same, bit for bit. One
 * caller at a time uses the pool (a kernel called from two threads at once, as XLA's may, makes its own threads
 * for the second call: pool_begin says no). After fork() the child has no worker threads: the pool starts empty
 * there (pthread_atfork).
 */
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define POOL_MAX 16
/* How long an idle worker spins before it sleeps (ns). */
#define SPIN_NS 1000000L
/* The largest gradient buffer a worker keeps between calls, in doubles (2 MB). */
#define BUF_MAX ((size_t)1 << 18)

typedef void *(*pool_fn)(void *);

static struct {
    pthread_mutex_t busy, m;
    pthread_cond_t cv;
    int workers;        /* threads 1 .. workers exist (0: none yet) */
    unsigned gen;       /* the current call's number (atomic; written under m) */
    int pending;        /* workers still on the current call (atomic) */
    unsigned task[POOL_MAX]; /* the call worker t takes part in (atomic): a worker left out of one call that
                              * looks late must not take the next one's job before that call is posted */
    pool_fn fn;
    char *base;
    size_t size;
    double *zero[POOL_MAX];
    size_t zlen[POOL_MAX];
    double *buf[POOL_MAX];
    size_t cap[POOL_MAX];
    int atfork;
} P = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_MUTEX_INITIALIZER, PTHREAD_COND_INITIALIZER};

static inline void relax(void) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ __volatile__("yield");
#endif
}

static long long elapsed_ns(const struct timespec *t0) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (long long)(t.tv_sec - t0->tv_sec) * 1000000000LL + (t.tv_nsec - t0->tv_nsec);
}

static void *pool_worker(void *arg) {
    uintptr_t a = (uintptr_t)arg;
    int t = (int)(a & 0xff);
    unsigned seen = (unsigned)(a >> 8);
    for (;;) {
        unsigned g;
        struct timespec t0;
        clock_gettime(CLOCK_MONOTONIC, &t0);
        int spins = 0;
        while ((g = __atomic_load_n(&P.gen, __ATOMIC_ACQUIRE)) == seen) {
            relax();
            if (++spins < 256) continue;
            spins = 0;
            if (elapsed_ns(&t0) < SPIN_NS) continue;
            pthread_mutex_lock(&P.m);
            while ((g = __atomic_load_n(&P.gen, __ATOMIC_ACQUIRE)) == seen) pthread_cond_wait(&P.cv, &P.m);
            pthread_mutex_unlock(&P.m);
            break;
        }
        seen = g;
        if (__atomic_load_n(&P.task[t], __ATOMIC_RELAXED) == g) {
            if (P.zero[t]) memset(P.zero[t], 0, P.zlen[t] * sizeof(double));
            P.fn(P.base + (size_t)t * P.size);
            __atomic_sub_fetch(&P.pending, 1, __ATOMIC_RELEASE);
        }
    }
    return NULL;
}

static void pool_after_fork(void) {
    pthread_mutex_init(&P.busy, NULL);
    pthread_mutex_init(&P.m, NULL);
    pthread_cond_init(&P.cv, NULL);
    P.workers = 0;
    for (int t = 0; t < POOL_MAX; t++) P.buf[t] = NULL, P.cap[t] = 0; /* (the parent's copies: not freed here) */
}

/* The pool for a call on nt threads (2 <= nt <= POOL_MAX), its workers made where missing: 1, or 0 where
 * another caller holds it or a thread cannot be made (the caller then makes its own threads). */
int pool_begin(int nt) {
    if (nt < 2 || nt > POOL_MAX || pthread_mutex_trylock(&P.busy) != 0) return 0;
    if (!P.atfork) P.atfork = pthread_atfork(NULL, NULL, pool_after_fork) == 0 ? 1 : -1;
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
    while (P.workers < nt - 1) {
        pthread_t id;
        uintptr_t arg = ((uintptr_t)P.gen << 8) | (uintptr_t)(P.workers + 1);
        if (pthread_create(&id, &attr, pool_worker, (void *)arg) != 0) break;
        P.workers++;
    }
    pthread_attr_destroy(&attr);
    if (P.workers < nt - 1) {
        pthread_mutex_unlock(&P.busy);
        return 0;
    }
    return 1;
}

/* Worker t's gradient buffer of len doubles for this call (zeroed by the worker before its job: pool_run), or
 * NULL where it would be larger than BUF_MAX or cannot be had (the caller allocates one). */
double *pool_buffer(int t, size_t len) {
    if (len > BUF_MAX) return NULL;
    if (P.cap[t] < len) {
        double *b = realloc(P.buf[t], (len ? len : 1) * sizeof(double));
        if (!b) return NULL;
        P.buf[t] = b;
        P.cap[t] = len;
    }
    return P.buf[t];
}

/* fn(base + t * size) for t < nt, job 0 in this thread, the others on the workers (each first zeroes zlen[t]
 * doubles at zero[t], where not NULL); returns when all are done. Between pool_begin and pool_end. */
void pool_run(int nt, pool_fn fn, char *base, size_t size, double *const *zero, const size_t *zlen) {
    unsigned g = P.gen + 1;
    for (int t = 1; t < nt; t++) __atomic_store_n(&P.task[t], g, __ATOMIC_RELAXED);
    P.fn = fn;
    P.base = base;
    P.size = size;
    for (int t = 1; t < nt; t++) P.zero[t] = zero ? zero[t] : NULL, P.zlen[t] = zlen ? zlen[t] : 0;
    __atomic_store_n(&P.pending, nt - 1, __ATOMIC_RELAXED);
    pthread_mutex_lock(&P.m);
    __atomic_add_fetch(&P.gen, 1, __ATOMIC_RELEASE);
    pthread_cond_broadcast(&P.cv);
    pthread_mutex_unlock(&P.m);
    fn(base);
    long spins = 0;
    while (__atomic_load_n(&P.pending, __ATOMIC_ACQUIRE) > 0)
        if (++spins % 4096 == 0) sched_yield();
        else relax();
}

void pool_end(void) { pthread_mutex_unlock(&P.busy); }
