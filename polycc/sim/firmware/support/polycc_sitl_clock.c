/*
 * polycc_sitl_clock.c -- LD_PRELOAD shim that makes the bridge the clock of a SITL cf2.
 *
 * The FreeRTOS POSIX port ticks on SIGALRM from setitimer(ITIMER_REAL, 1 ms)
 * (vendor/FreeRTOS/portable/ThirdParty/GCC/Posix/port.c, prvSetupTimerInterrupt).  Standard
 * signals do not queue: when cf2 is not scheduled for a few ms the pending SIGALRMs collapse
 * into one and the firmware loses ticks, so its clock (xTaskGetTickCount, usecTimestamp, the
 * Kalman predictor's dt, the HL planner, the supervisor) runs slower than the physics.
 *
 * With POLYCC_SITL_TICK_FD=<fd> in the environment (a pipe read end inherited from the
 * supervisor), this shim
 *   - turns cf2's setitimer(ITIMER_REAL, ...) into "start the tick thread" (no real timer);
 *   - runs a thread (all signals blocked, so it never runs the port's handler itself) that
 *     reads the pipe and, per byte, raises one SIGALRM, waiting until the previous one has been
 *     taken by the running FreeRTOS task, so no tick is ever lost;
 *   - exits cf2 when the pipe reaches EOF (the bridge is gone).
 * One byte per 1 ms physics step, so firmware time == physics time.
 *
 * The reader's fair share (also only with POLYCC_SITL_TICK_FD).  The fork's socket reader task
 * (src/hal/src/socketlink.c:83, priority 2) blocks in poll(-1) and yields (vTaskDelay(1)) only
 * when poll fails with EINTR, i.e. when the tick's SIGALRM lands while it is inside poll.
 * FreeRTOS counts a task blocked in poll as running, so the priority-1 tasks (the app, log,
 * param) run only in the ticks after such an EINTR.  The bridge sends each step's IMU just
 * before its tick byte: on an idle host the reader is back in poll before the tick arrives; on
 * a loaded one it is often still runnable with the IMU when the tick is taken, poll returns the
 * IMU instead of EINTR, and the reader holds the CPU for the whole next tick.  The app then
 * made 36-61 of its 100 decisions per second.  So this shim also wraps
 *   - sigaction(SIGALRM): the port's tick handler runs behind a trampoline that counts the
 *     ticks taken on each thread (thread-local, so a task counts only ticks it was running for);
 *   - poll(..., -1): a thread that took a tick since its last EINTR (while it was running,
 *     between two polls or in one whose data won the race) first gets what is already in the
 *     socket, then EINTR as soon as nothing is, as it would have if the tick had landed inside
 *     a blocked poll.  Otherwise poll blocks as before.
 * Every tick the reader was running for thus yields once, whatever the host's thread timing,
 * and no datagram waits behind a yield that was already in the socket; none is lost or
 * reordered.
 *
 * Always: stdout line-buffered (replaces `stdbuf -oL`, which would need its own LD_PRELOAD).
 * Without POLYCC_SITL_TICK_FD: setitimer passes through unchanged (the fork's wall clock).
 *
 * Built by polycc/sim/firmware/build.py as libpolycc_sitl_clock.so; no firmware code, libc only.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

/* glibc declares setitimer with an enum first argument under _GNU_SOURCE */
#if defined(__GLIBC__) && defined(_GNU_SOURCE)
typedef __itimer_which_t polycc_which_t;
#else
typedef int polycc_which_t;
#endif

static int tick_fd = -1;
static pthread_t tick_thread;
static int tick_started;
static volatile unsigned long ticks_raised;

static int (*real_setitimer)(polycc_which_t, const struct itimerval *, struct itimerval *);
static int (*real_sigaction)(int, const struct sigaction *, struct sigaction *);
static int (*real_poll)(struct pollfd *, nfds_t, int);

/* the port's SIGALRM handler, and the ticks taken / yielded for on this thread */
static void (*port_tick_handler)(int);
static void (*port_tick_action)(int, siginfo_t *, void *);
static __thread volatile unsigned long ticks_here __attribute__((tls_model("initial-exec")));
static __thread unsigned long ticks_yielded __attribute__((tls_model("initial-exec")));

__attribute__((constructor)) static void polycc_sitl_clock_init(void)
{
    const char *fd = getenv("POLYCC_SITL_TICK_FD");
    setvbuf(stdout, NULL, _IOLBF, 0);
    real_setitimer = (int (*)(polycc_which_t, const struct itimerval *, struct itimerval *))dlsym(RTLD_NEXT,
                                                                                                   "setitimer");
    real_sigaction = (int (*)(int, const struct sigaction *, struct sigaction *))dlsym(RTLD_NEXT, "sigaction");
    real_poll = (int (*)(struct pollfd *, nfds_t, int))dlsym(RTLD_NEXT, "poll");
    if (fd && *fd) {
        tick_fd = atoi(fd);
    }
}

static int alrm_pending(void)
{
    sigset_t s;
    sigemptyset(&s);
    if (sigpending(&s) != 0) {
        return 0;
    }
    return sigismember(&s, SIGALRM) == 1;
}

static void *tick_main(void *arg)
{
    unsigned char buf[256];
    sigset_t all;
    const struct timespec pause = {0, 20000}; /* 20 us */
    (void)arg;
    sigfillset(&all);
    pthread_sigmask(SIG_BLOCK, &all, NULL);
    for (;;) {
        ssize_t n = read(tick_fd, buf, sizeof buf);
        if (n == 0) {
            fprintf(stderr, "polycc_sitl_clock: tick pipe closed (bridge gone), exiting\n");
            _exit(0);
        }
        if (n < 0) {
            if (errno == EINTR) {
                continue;
            }
            fprintf(stderr, "polycc_sitl_clock: read tick pipe: %s\n", strerror(errno));
            _exit(1);
        }
        for (ssize_t i = 0; i < n; ++i) {
            /* never let two SIGALRMs collapse into one */
            while (alrm_pending()) {
                nanosleep(&pause, NULL);
            }
            kill(getpid(), SIGALRM);
            ++ticks_raised;
        }
    }
    return NULL;
}

int setitimer(polycc_which_t which, const struct itimerval *new_value, struct itimerval *old_value)
{
    if (tick_fd < 0 || which != ITIMER_REAL) {
        return real_setitimer(which, new_value, old_value);
    }
    if (old_value) {
        memset(old_value, 0, sizeof *old_value);
    }
    if (new_value && (new_value->it_value.tv_sec || new_value->it_value.tv_usec) && !tick_started) {
        sigset_t all, old;
        sigfillset(&all);
        pthread_sigmask(SIG_BLOCK, &all, &old);  /* the thread starts with everything blocked */
        if (pthread_create(&tick_thread, NULL, tick_main, NULL) != 0) {
            pthread_sigmask(SIG_SETMASK, &old, NULL);
            return real_setitimer(which, new_value, old_value);
        }
        pthread_sigmask(SIG_SETMASK, &old, NULL);
        tick_started = 1;
    }
    return 0;
}

static void tick_trampoline(int sig)
{
    ++ticks_here;
    port_tick_handler(sig);
}

static void tick_trampoline_info(int sig, siginfo_t *info, void *uc)
{
    ++ticks_here;
    port_tick_action(sig, info, uc);
}

int sigaction(int sig, const struct sigaction *act, struct sigaction *old)
{
    if (tick_fd < 0 || sig != SIGALRM || act == NULL) {
        return real_sigaction(sig, act, old);
    }
    struct sigaction wrapped = *act;
    if (act->sa_flags & SA_SIGINFO) {
        port_tick_action = act->sa_sigaction;
        wrapped.sa_sigaction = tick_trampoline_info;
    } else if (act->sa_handler != SIG_IGN && act->sa_handler != SIG_DFL) {
        port_tick_handler = act->sa_handler;
        wrapped.sa_handler = tick_trampoline;
    }
    return real_sigaction(sig, &wrapped, old);
}

int poll(struct pollfd *fds, nfds_t nfds, int timeout)
{
    if (tick_fd < 0 || timeout >= 0) {
        return real_poll(fds, nfds, timeout);
    }
    if (ticks_here != ticks_yielded) {  /* a tick came while this task was running */
        int ready = real_poll(fds, nfds, 0);
        if (ready != 0) {
            return ready;               /* first take what is already there (the step's IMU) */
        }
        ticks_yielded = ticks_here;     /* then yield for the tick */
        errno = EINTR;
        return -1;
    }
    int r = real_poll(fds, nfds, timeout);
    if (r < 0 && errno == EINTR) {
        ticks_yielded = ticks_here;     /* the tick landed inside poll: the caller yields for it */
    }
    return r;
}
