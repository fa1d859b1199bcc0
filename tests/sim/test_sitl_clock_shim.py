"""The SITL clock shim's poll: every tick a task was running for makes it yield once, after
it has taken what was already there (fast, no firmware).

The fork's socket reader blocks in poll(-1) and yields only on EINTR.  On a loaded host the tick's SIGALRM
was often taken just before poll returned the step's IMU, so no EINTR came, the reader kept the CPU and the
app (priority 1) made 36-61 of its 100 decisions per second.  A probe program stands in for the reader: it
installs a SIGALRM handler and starts the "timer" as the FreeRTOS port does, and raises ticks through the
shim's pipe as the bridge does.
"""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from polycc.sim.firmware.build import CLOCK_SHIM_SOURCE

PROBE = r"""
#define _GNU_SOURCE
#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

static volatile int handled;
static void on_tick(int s) { (void)s; ++handled; }

static void tick_outside_poll(int w)
{
    int before = handled;
    if (write(w, "\1", 1) != 1) { exit(3); }
    while (handled == before) { }   /* taken while this "task" runs user code */
}

static const char *rc(int r) { return r > 0 ? "data" : (r < 0 && errno == EINTR) ? "EINTR" : "other"; }

int main(void)
{
    int w = atoi(getenv("PROBE_TICK_W"));
    struct sigaction sa = {0};
    sa.sa_handler = on_tick;
    sigfillset(&sa.sa_mask);
    sigaction(SIGALRM, &sa, NULL);
    struct itimerval it = {{0, 1000}, {0, 1000}};
    setitimer(ITIMER_REAL, &it, NULL);
    int sp[2];
    char b;
    if (socketpair(AF_UNIX, SOCK_DGRAM, 0, sp) != 0) { return 4; }
    struct pollfd pf = {sp[0], POLLIN, 0};

    /* 1: data ready, no tick: poll returns it */
    if (write(sp[1], "a", 1) != 1) { return 5; }
    printf("ready %s\n", rc(poll(&pf, 1, -1)));
    if (recv(sp[0], &b, 1, 0) != 1) { return 6; }

    /* 2: a tick taken between two polls with data waiting: the data first, then the yield (nothing is
       left), then a plain blocking poll again */
    tick_outside_poll(w);
    if (write(sp[1], "b", 1) != 1) { return 5; }
    printf("tick-then-data %s", rc(poll(&pf, 1, -1)));
    if (recv(sp[0], &b, 1, 0) != 1) { return 6; }
    printf(" %s", rc(poll(&pf, 1, -1)));
    if (write(sp[1], "b", 1) != 1) { return 5; }
    printf(" %s\n", rc(poll(&pf, 1, -1)));
    if (recv(sp[0], &b, 1, 0) != 1) { return 6; }

    /* 3: no data, a tick lands while blocked: EINTR once; the next poll returns data, not a second EINTR */
    if (write(w, "\1", 1) != 1) { return 3; }
    printf("blocked %s", rc(poll(&pf, 1, -1)));
    if (write(sp[1], "c", 1) != 1) { return 5; }
    printf(" %s\n", rc(poll(&pf, 1, -1)));
    if (recv(sp[0], &b, 1, 0) != 1) { return 6; }

    /* 4: a finite timeout is never touched */
    tick_outside_poll(w);
    if (write(sp[1], "d", 1) != 1) { return 5; }
    printf("timeout %s\n", rc(poll(&pf, 1, 1000)));
    printf("ticks %d\n", handled);
    return 0;
}
"""


@pytest.fixture(scope="module")
def probe(tmp_path_factory):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (the SITL build needs one too: apt-get install build-essential)")
    d = tmp_path_factory.mktemp("clockshim")
    (d / "probe.c").write_text(PROBE)
    subprocess.run([cc, "-O2", "-Wall", "-fPIC", "-shared", "-o", str(d / "shim.so"), str(CLOCK_SHIM_SOURCE),
                    "-ldl", "-lpthread"], check=True)
    subprocess.run([cc, "-O2", "-Wall", "-o", str(d / "probe"), str(d / "probe.c")], check=True)
    return d


def _run(probe, with_clock: bool) -> str:
    r, w = os.pipe()
    env = dict(os.environ, LD_PRELOAD=str(probe / "shim.so"), PROBE_TICK_W=str(w))
    if with_clock:
        env["POLYCC_SITL_TICK_FD"] = str(r)
    try:
        p = subprocess.run([str(probe / "probe")], env=env, pass_fds=(r, w), capture_output=True, text=True,
                           timeout=20)
    finally:
        os.close(r)
        os.close(w)
    assert p.returncode == 0, p
    return p.stdout


def test_a_tick_taken_outside_poll_yields_once_the_socket_is_empty(probe):
    out = _run(probe, with_clock=True).splitlines()
    assert out == ["ready data", "tick-then-data data EINTR data", "blocked EINTR data", "timeout data", "ticks 3"], out


def test_without_the_bridge_clock_poll_is_untouched(probe):
    """No POLYCC_SITL_TICK_FD: the fork's own setitimer and a plain poll (the probe's pipe ticks go nowhere, so
    only the real 1 ms timer ticks; a tick between polls no longer turns into EINTR)."""
    out = _run(probe, with_clock=False).splitlines()
    assert out[0] == "ready data" and out[1].endswith("data"), out
