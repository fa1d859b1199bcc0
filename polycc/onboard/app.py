"""The Crazyflie app's interface as the ground sees it (``firmware_app/src/polycc_app.h``).

Names of the ``polycc`` log variable ``status`` (POLYCC_STATUS_* in polycc_app.h; a test checks
the two agree), and the ``polycc`` parameter and log groups.
"""

from __future__ import annotations

STATUS_NAMES = {
    0: "disabled", 1: "ok", 2: "no estimate", 3: "bad estimate", 4: "stale estimate", 5: "inside",
    6: "kernel invalid", 7: "not flying", 8: "waiting for the high-level commander", 9: "controller is not PID",
    10: "link lost", 11: "supervisor locked or crashed", 12: "scene too slow", 13: "neighbour lost",
    14: "handing over",
}
# What each status means for the user, in words (`polycc fly` prints these).
STATUS_TEXT = {
    0: "disabled: the app sends nothing (after a hand-over the high-level commander holds the position)",
    1: "flying through the safety filter",
    2: "no stateEstimate in the log TOC: holding position",
    3: "the position estimate is invalid or too uncertain: holding position",
    4: "the position estimate is not updating: holding position",
    5: "inside an obstacle's safety margin (psi < 0): holding position",
    6: "the kernel refused the parameters, goal or state: holding position",
    7: "on the ground or motors off: take off first (high-level takeoff), nothing is sent",
    8: "waiting for the high-level commander's takeoff or go_to to finish",
    9: "stabilizer.controller is not PID (set it to 1): enable refused",
    10: "link lost: handed over to a high-level landing, enable cleared",
    11: "the supervisor has locked the vehicle or detected a crash/tumble: nothing is sent",
    12: "the scene's worst-case evaluation does not fit even 10 Hz: rebuild with --rate-hz",
    13: "a neighbour's position report is older than 0.5 s, or fewer neighbours than polycc.swarmN are known: "
        "holding position (docs/swarm.md)",
    14: "disabled in the air: holding the hand-over point until the z integral has decayed, then the high-level "
        "commander holds",
}
FLYING = {1, 2, 3, 4, 5, 6, 13, 14}  # statuses in which the app streams setpoints (owns the vehicle)
STOP_REASONS = {5, 6, 9, 10, 11, 12}  # statuses that end a `polycc fly` run with an error
REPLY_FORMAT = "<BBffff"
"""App-channel reply head (POLYCC_APP_REPLY_BYTES): status, enable, psi (m), estimate x, y, z (m); then an
echo of the first bytes of the request."""
PARAM_GROUP = "polycc"
LOG_GROUP = "polycc"

# polycc_app.h: the app's rate choice (a test checks these against the header).
DEFAULT_RATE_HZ = 500  # POLYCC_APP_DEFAULT_RATE_HZ
MIN_RATE_HZ = 10  # POLYCC_APP_MIN_RATE_HZ
CPU_HZ = 168_000_000  # POLYCC_APP_CPU_HZ
CPU_SHARE_PERCENT = 50  # POLYCC_APP_CPU_SHARE_PERCENT: the worst case must fit this share of a period
TICK_RATE_HZ = 1000  # FreeRTOS configTICK_RATE_HZ on the Crazyflie
SWARM_WORST_CYCLES = 6000  # POLYCC_APP_SWARM_WORST_CYCLES: the neighbour terms' bound, added to the scene's
NBR_MAGIC = 0x4E  # POLYCC_APP_NBR_MAGIC: app-channel neighbour report
NBR_FORGET = 0xFFFF  # POLYCC_APP_NBR_FORGET: this age removes the neighbour (it landed or left)
NBR_FORMAT = "<BBfffHH"  # 'N', id, x, y, z (m), age (ms), radius (mm): POLYCC_APP_NBR_BYTES = 18
P2P_PORT = 0x0B  # POLYCC_APP_P2P_PORT: the same record as the payload of a P2P broadcast on this P2P port
P2P_RING = 16  # POLYCC_APP_P2P_RING: P2P records the app holds between two of its ticks


def app_rate_hz(worst_cycles: int, requested_hz: int = DEFAULT_RATE_HZ) -> int | None:
    """The loop rate (Hz) the app runs a scene at: ``requested_hz`` rounded to whole 1 ms ticks and
    lowered until ``worst_cycles`` (POLYCC_SCENE_WORST_CYCLES) fits CPU_SHARE_PERCENT of a period,
    as ``periodTicks()`` in polycc_app.c does; None if it does not fit even MIN_RATE_HZ (status 12)."""
    per_tick = CPU_HZ // TICK_RATE_HZ
    avail = per_tick * CPU_SHARE_PERCENT
    t_min = max(1, -(-(int(worst_cycles) + SWARM_WORST_CYCLES) * 100 // avail))
    if t_min > TICK_RATE_HZ // MIN_RATE_HZ:
        return None
    r = max(MIN_RATE_HZ, int(requested_hz))
    t = max(1, (TICK_RATE_HZ + r // 2) // r, t_min)
    return TICK_RATE_HZ // t


def pack_forget(nid: int) -> bytes:
    """The app-channel record that removes neighbour ``nid`` from the app's table."""
    import struct

    return struct.pack(NBR_FORMAT, NBR_MAGIC, int(nid) & 0xFF, 0.0, 0.0, 0.0, NBR_FORGET, 0)


def pack_neighbour(nid: int, pos, age_ms: float, radius_m: float) -> bytes:
    """The app-channel neighbour report (POLYCC_APP_NBR_BYTES, docs/swarm.md): id, position (m), age
    and radius rounded up to whole ms / mm (so the app's buffer is never smaller than stated)."""
    import math
    import struct

    age = min(NBR_FORGET - 1, max(0, math.ceil(age_ms)))  # a stated age never means "forget"
    rmm = min(65535, max(0, math.ceil(radius_m * 1000.0 - 1e-9)))
    return struct.pack(NBR_FORMAT, NBR_MAGIC, int(nid) & 0xFF, float(pos[0]), float(pos[1]), float(pos[2]), age, rmm)
