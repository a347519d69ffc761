/* The crew of helper threads that share a kernel's blocks with the calling thread
 * (o3dvis/nn/native/threads.py, kernel_threads): crew_run and crew_workers, declared in kernels.h
 * beside crew_claim, by which the workers claim a job's items. */

#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <time.h>

#include "kernels.h"

/* A crew of helper threads kept for the life of the process, that run a share of a kernel's work
 * beside the calling thread: a kernel of a few hundred microseconds cannot pay for starting a thread
 * (tens of microseconds here), so the helpers are started once and, after each piece of work, wait
 * for the next one spinning for a while (CREW_SPIN_NS), then asleep on a condition variable. The
 * work is claimed item by item from a shared counter, so a helper that starts late (or not at all,
 * on a busy machine) only takes fewer items: the caller runs what is left. A forked child starts
 * with no helpers. */
#define CREW_SPIN_NS 50000

static struct {
    pthread_mutex_t lock;
    pthread_cond_t wake;
    struct crew_job *job; /* the one running, NULL between */
    uint64_t posted;      /* jobs posted so far */
    int helpers, sleeping, first_worker;
} crew = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_COND_INITIALIZER, NULL, 0, 0, 0, 0};
static pthread_once_t crew_once = PTHREAD_ONCE_INIT;

static inline void cpu_relax(void) { /* a spinning thread's pause, which leaves the core's units to others */
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ volatile("yield");
#endif
}

static uint64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000u + (uint64_t)t.tv_nsec;
}

static void *crew_helper(void *unused) {
    (void)unused;
    uint64_t seen = __atomic_load_n(&crew.posted, __ATOMIC_ACQUIRE);
    for (;;) {
        const uint64_t until = now_ns() + CREW_SPIN_NS;
        while (__atomic_load_n(&crew.posted, __ATOMIC_ACQUIRE) == seen && now_ns() < until)
            for (int i = 0; i < 64; i++) cpu_relax();
        pthread_mutex_lock(&crew.lock);
        while (crew.posted == seen) {
            crew.sleeping++;
            pthread_cond_wait(&crew.wake, &crew.lock);
            crew.sleeping--;
        }
        seen = crew.posted;
        struct crew_job *job = crew.job;
        int worker = -1;
        if (job != NULL && crew.first_worker < job->workers) {
            worker = crew.first_worker++;
            __atomic_add_fetch(&job->joined, 1, __ATOMIC_ACQ_REL);
        }
        pthread_mutex_unlock(&crew.lock);
        if (worker >= 0) {
            job->run(job, worker);
            __atomic_sub_fetch(&job->joined, 1, __ATOMIC_RELEASE);
        }
    }
    return NULL;
}

static void crew_forked(void) { /* the child of a fork has this thread only */
    pthread_mutex_init(&crew.lock, NULL);
    pthread_cond_init(&crew.wake, NULL);
    crew.job = NULL, crew.helpers = crew.sleeping = 0;
}

static void crew_register(void) { pthread_atfork(NULL, NULL, crew_forked); }

/* Runs job->run on the calling thread (worker 0) and on up to job->workers - 1 helpers (workers 1,
 * 2, ...), starting helpers that are missing; returns when every worker that joined has returned. */
void crew_run(struct crew_job *job) {
    job->next = 0, job->joined = 0;
    if (job->workers > 1) {
        pthread_once(&crew_once, crew_register);
        pthread_mutex_lock(&crew.lock);
        while (crew.helpers < job->workers - 1 && crew.helpers < CREW_MAX) {
            pthread_t thread;
            pthread_attr_t attr;
            sigset_t all, before; /* a helper takes no signal: they go to the threads of the program */
            sigfillset(&all);
            pthread_attr_init(&attr);
            pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
            pthread_sigmask(SIG_SETMASK, &all, &before);
            const int failed = pthread_create(&thread, &attr, crew_helper, NULL);
            pthread_sigmask(SIG_SETMASK, &before, NULL);
            pthread_attr_destroy(&attr);
            if (failed) break; /* fewer helpers: the caller claims more */
            crew.helpers++;
        }
        crew.job = job, crew.first_worker = 1;
        __atomic_add_fetch(&crew.posted, 1, __ATOMIC_RELEASE);
        if (crew.sleeping) pthread_cond_broadcast(&crew.wake);
        pthread_mutex_unlock(&crew.lock);
    }
    job->run(job, 0);
    if (job->workers > 1) {
        pthread_mutex_lock(&crew.lock);
        if (crew.job == job) crew.job = NULL; /* no helper joins from now on (another caller's may) */
        pthread_mutex_unlock(&crew.lock);
        for (int spins = 0; __atomic_load_n(&job->joined, __ATOMIC_ACQUIRE); spins++)
            if (spins < 4096) cpu_relax();
            else sched_yield();
    }
}

/* The threads a job of items shares out among: threads, but no more than the items. */
int crew_workers(int threads, int64_t items) { return items < threads ? (items > 1 ? (int)items : 1) : threads; }
