"""Drive the real cfclient GUI (PyQt6, offscreen) the way a user does: start it, let its own scan find
the Crazyflies on ``udp://127.0.0.1:19850..19859`` (cflib's UDP scan range), pick the given URI in the
interface box, press Connect, and keep its tabs running against the connected Crazyflie.

Run as ``python -m polycc.testing.cfclient_connect URI [--seconds S] [--timeout S]``; it prints one JSON
line (``connected``, the TOC sizes, the battery voltage cfclient logged, the errors cfclient raised or
logged) and exits 0 only when cfclient connected, received log data and raised no error.  A subprocess,
so Qt and cfclient's global config never touch the test process; ``HOME``/``XDG_CONFIG_HOME`` should point
at a scratch folder so the user's cfclient config is not read or written.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
import traceback


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("uri")
    ap.add_argument("--seconds", type=float, default=5.0, help="keep the tabs running this long once connected (s)")
    ap.add_argument("--timeout", type=float, default=120.0, help="give up connecting after this long (s)")
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

    errors: list[str] = []
    warnings: list[str] = []

    class _Errors(logging.Handler):
        def emit(self, record):
            if record.levelno >= logging.ERROR:
                errors.append(f"{record.name}: {record.getMessage()}")
            elif record.levelno >= logging.WARNING and not record.name.startswith("cflib.crazyflie.toccache"):
                warnings.append(f"{record.name}: {record.getMessage()}")

    logging.basicConfig(level=logging.WARNING)
    logging.getLogger().addHandler(_Errors())
    sys.excepthook = lambda *e: errors.append("".join(traceback.format_exception(*e)))
    threading.excepthook = lambda a: errors.append("".join(traceback.format_exception(a.exc_type, a.exc_value,
                                                                                      a.exc_traceback)))
    from PyQt6.QtWidgets import QApplication, QMessageBox

    # cfclient reports link failures and log errors in modal boxes, which would block offscreen.
    def boxed(_parent, title, text, *a, **k):
        errors.append(f"{title}: {text}")

    for name in ("critical", "warning", "about", "information"):
        setattr(QMessageBox, name, staticmethod(boxed))

    app = QApplication(["cfclient"])
    from cfclient.ui.main import MainUI, UIState

    ui = MainUI()
    ui.show()
    battery: list[float] = []
    ui.batteryUpdatedSignal.connect(lambda _ts, data, _conf: battery.append(float(data["pm.vbat"])))
    # Where a connection stalls: cflib's setup runs link -> platform info -> log TOC -> memories -> param TOC
    # (-> connected); each stage's callback is looked up on the instance when it is due, so wrapping records it.
    t0 = time.monotonic()
    stages: list[list] = []

    def _stage(name, fn):
        def wrapped(*a, **k):
            stages.append([name, round(time.monotonic() - t0, 2)])
            return fn(*a, **k)
        return wrapped

    ui.cf.link_established.add_callback(lambda _uri: stages.append(["link", round(time.monotonic() - t0, 2)]))
    for name in ("_platform_info_fetched", "_log_toc_updated_cb",
                 "_mems_updated_cb", "_param_toc_updated_cb"):
        if hasattr(ui.cf, name):
            setattr(ui.cf, name, _stage(name.strip("_").removesuffix("_cb"), getattr(ui.cf, name)))
    cm = ui._connectivity_manager
    combo = cm._ui_elements[0].interface_combo
    result = {"uri": args.uri, "connected": False, "found": [], "errors": errors, "warnings": warnings}

    def pump(seconds: float, until=lambda: False) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            app.processEvents()
            if until():
                return True
            time.sleep(0.01)
        return until()

    def found() -> bool:
        return any(combo.itemText(i) == args.uri for i in range(combo.count()))

    deadline = time.monotonic() + args.timeout
    while not found() and time.monotonic() < deadline:  # cfclient scans at start; rescan as a user would
        if not pump(3.0, found) and ui.uiState != UIState.SCANNING:
            ui._scan_from_button(cm.get_address())
    result["found"] = [combo.itemText(i) for i in range(1, combo.count())]
    result["found_s"] = round(time.monotonic() - t0, 2)
    if found():
        combo.setCurrentText(args.uri)
        stages.append(["click Connect", result["found_s"]])
        cm._ui_elements[0].connect_button.click()
        result["connected"] = pump(max(1.0, deadline - time.monotonic()), lambda: ui.uiState == UIState.CONNECTED)
    result["stages"] = stages  # [stage, s since start]
    result["ui_state"] = str(ui.uiState)
    result["cf_state"] = ui.cf.state
    if not result["connected"]:
        result["toc_sizes"] = {k: sum(len(g) for g in getattr(getattr(sub, "toc", None), "toc", {}).values())
                               for k, sub in (("log", ui.cf.log), ("param", ui.cf.param))}
    if result["connected"]:
        pump(args.seconds)
        result["params"] = len(ui.cf.param.toc.toc)  # groups
        result["log_groups"] = len(ui.cf.log.toc.toc)
        result["battery_v"] = battery[-1] if battery else None
        result["has_vbat"] = ui.cf.log.toc.get_element_by_complete_name("pm.vbat") is not None
        result["still_connected"] = ui.uiState == UIState.CONNECTED
        cm._ui_elements[0].connect_button.click()  # Disconnect
        pump(3.0, lambda: ui.uiState == UIState.DISCONNECTED)
    ui.cf.close_link()
    print(json.dumps(result), flush=True)
    ok = result["connected"] and result.get("still_connected") and (battery or not result["has_vbat"]) and not errors
    os._exit(0 if ok else 1)  # cfclient leaves non-daemon threads (input readers) behind



def free_scan_port() -> int:
    """A free UDP port in cflib's scan range 19850..19859 (cfclient only lists what its scan finds)."""
    import socket

    for port in range(19850, 19860):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("UDP ports 19850..19859 are all in use; cfclient's scan cannot find another device")


def run_cfclient(uri: str, home, seconds: float = 5.0, timeout: float = 180.0) -> dict:
    """Run :func:`main` in a subprocess with a scratch ``home``; return its JSON result."""
    import subprocess

    env = dict(os.environ, HOME=str(home), XDG_CONFIG_HOME=str(home), QT_QPA_PLATFORM="offscreen")
    proc = subprocess.run([sys.executable, "-m", "polycc.testing.cfclient_connect", uri, "--seconds", str(seconds),
                           "--timeout", str(timeout)], capture_output=True, text=True, env=env, timeout=timeout + 60)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if not lines:
        return {"connected": False, "still_connected": False, "errors": [proc.stdout[-2000:] + proc.stderr[-4000:]],
                "battery_v": None}
    return json.loads(lines[-1])


if __name__ == "__main__":
    sys.exit(main())
