"""The Crazyflie app's interface as the ground sees it (``firmware_app/src/polycc_app.h``).

Names of the ``polycc`` log variable ``status`` (POLYCC_STATUS_* in polycc_app.h; a test checks
the two agree), and the ``polycc`` parameter and log groups.
"""

from __future__ import annotations

STATUS_NAMES = {0: "disabled", 1: "ok", 2: "no estimate", 3: "bad estimate", 4: "stale estimate", 5: "inside",
                6: "kernel invalid"}
PARAM_GROUP = "polycc"
LOG_GROUP = "polycc"
