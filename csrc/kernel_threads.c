/* The library's own entries (its ABI version, the chunk size, the helper threads' spin-wait) and
 * what every multi-threaded entry runs on: a pool of scratch buffers and the chunk runner.
 *
 * Threads: Python threads (a ctypes call releases the GIL) call the same entry at once; each claims
 * the next chunk from a shared atomic counter ((1,) int64, 0 at the start of a call) until none is
 * left, and the entry returns how many chunks its thread did (affine_deformers/accel/threads.py). */
#include "affine_kernel.h"
#include "affine_internal.h"

#include <stdlib.h>

#if defined(__x86_64__) || defined(_M_X64)
#include <immintrin.h>
#define CPU_RELAX() _mm_pause()
#else
#define CPU_RELAX() ((void)0)
#endif

int32_t ak_abi_version(void) { return AK_ABI_VERSION; }

int64_t ak_chunk(void) { return CHUNK; }

/* ------------------------------------------------------------------------------------------------
 * scratch: a few reusable buffers (a fresh large allocation per call would fault its pages in
 * every time); a call that finds none free allocates its own */

#define POOL 8
static void *pool_buf[POOL];
static size_t pool_size[POOL];
static int pool_busy[POOL];

static void *scratch_get(size_t bytes, int *slot) {
    for (int i = 0; i < POOL; i++) {
        if (__atomic_exchange_n(&pool_busy[i], 1, __ATOMIC_ACQUIRE) == 0) {
            if (pool_size[i] < bytes) {
                free(pool_buf[i]);
                pool_buf[i] = malloc(bytes);
                pool_size[i] = pool_buf[i] ? bytes : 0;
            }
            if (pool_buf[i]) {
                *slot = i;
                return pool_buf[i];
            }
            __atomic_store_n(&pool_busy[i], 0, __ATOMIC_RELEASE);
            break;
        }
    }
    *slot = -1;
    return malloc(bytes);
}

static void scratch_put(void *buf, int slot) {
    if (slot >= 0)
        __atomic_store_n(&pool_busy[slot], 0, __ATOMIC_RELEASE);
    else
        free(buf);
}

static inline int64_t claim(int64_t *counter) { return __atomic_fetch_add(counter, 1, __ATOMIC_RELAXED); }

int64_t ak_run_chunks(const void *args, chunk_fn chunk, int64_t n, int n_scratch_rows, int with_q,
                      int64_t *counter) {
    int64_t n_chunks = (n + CHUNK - 1) / CHUNK;
    size_t wbytes = sizeof(double) * (size_t)n_scratch_rows * STRIDE;
    int slot;
    char *buf = scratch_get(wbytes + (with_q ? sizeof(uint64_t) * CHUNK : 0), &slot);
    if (!buf) return -1;
    int64_t done = 0;
    for (;;) {
        int64_t c = claim(counter);
        if (c >= n_chunks) break;
        int64_t a = c * CHUNK;
        chunk(args, (double *)buf, with_q ? (uint64_t *)(buf + wbytes) : NULL, a, n - a < CHUNK ? n - a : CHUNK);
        done++;
    }
    scratch_put(buf, slot);
    return done;
}

/* Busy-wait until flag[0] != seen (1) or for n iterations (0). */
int32_t ak_spin_wait(const int64_t *flag, int64_t seen, int64_t n) {
    for (int64_t i = 0; i < n; i++) {
        if (__atomic_load_n(flag, __ATOMIC_RELAXED) != seen) return 1;
        CPU_RELAX();
    }
    return 0;
}
