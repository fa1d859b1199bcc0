"""Small helpers around Bitcraze's cflib sessions, shared by `polycc fly` and the real-firmware SITL.

* :func:`set_param` writes a param and waits for the Crazyflie's confirmation (cflib does not
  retransmit a lost write on UDP);
* :func:`close_without_stop` closes a session without cflib's parting ``send_setpoint(0, 0, 0, 0)``,
  which at CRTP priority stops the high-level commander and cuts the motors of a drone in the air;
* :func:`connect` opens a :class:`~cflib.crazyflie.syncCrazyflie.SyncCrazyflie` and waits for the TOCs
  and param values, with a wall-clock watchdog (cflib waits forever for a lost reply) and optional retries.
"""

from __future__ import annotations

import sys
import threading

from polycc.errors import PolyccError


def set_param(cf, name: str, value: float, timeout_s: float = 3.0) -> None:
    """Write a param and wait until the Crazyflie confirms it (cflib does not retransmit)."""
    done = threading.Event()
    group, short = name.split(".", 1)

    def cb(_name, _value):
        done.set()

    cf.param.add_update_callback(group=group, name=short, cb=cb)
    try:
        for _ in range(3):
            cf.param.set_value(name, value)
            if done.wait(timeout_s / 3):
                return
        raise PolyccError(f"no confirmation of {name} = {value:g} within {timeout_s:g} s; check the link")
    finally:
        try:
            cf.param.remove_update_callback(group=group, name=short, cb=cb)
        except Exception:  # older cflib without remove_update_callback
            pass


def close_without_stop(scf) -> None:
    """Close a cflib session without cflib's parting ``send_setpoint(0, 0, 0, 0)``, which at CRTP
    priority stops the high-level commander and cuts the motors of a drone still in the air."""
    cf = scf.cf
    link = getattr(cf, "link", None)
    if link is not None:
        try:
            link.close()
        except Exception:
            pass
        cf.link = None
    scf.close_link()


def connect(uri: str, timeout_s: float = 60.0, rw_cache: str | None = None, attempts: int = 1):
    """A connected ``SyncCrazyflie`` with its TOCs and all param values read, or a one-line error after
    ``attempts`` tries of ``timeout_s`` wall seconds each. ``rw_cache``: cflib's TOC cache folder (a repeat
    connect skips the TOC). A stalled try is closed (its cflib threads stop) before the next one, which is
    said on stderr.

    Why retry: cflib's serial driver drops a reply that arrives before its CRTP reader thread has first
    asked for one (``cflib.cpx.CPXRouter`` has no queue for CRTP until then), and waits for it for ever.
    A loaded host makes that thread late; a fresh session connects."""
    for k in range(1, max(1, attempts) + 1):
        try:
            return _connect_once(uri, timeout_s, rw_cache)
        except _Stalled as exc:
            if k >= attempts:
                raise PolyccError(str(exc)) from None
            print(f"polycc: {exc}; retrying with a fresh cflib session ({k + 1} of {attempts})", file=sys.stderr)


def _one_line(err: BaseException) -> str:
    """cflib's link errors carry their traceback in the message: keep what precedes it, on one line."""
    text = str(err).split("Traceback (most recent call last)")[0]
    return " ".join(text.split()) or type(err).__name__


class _Stalled(PolyccError):
    """A connect that neither finished nor failed within its time (retried by :func:`connect`)."""


def _connect_once(uri: str, timeout_s: float, rw_cache: str | None):
    try:
        import cflib.crtp
        from cflib.crazyflie import Crazyflie
        from cflib.crazyflie.syncCrazyflie import SyncCrazyflie
        from cflib.crtp.serialdriver import SerialDriver
    except ImportError:
        raise PolyccError("this needs Bitcraze's cflib: pip install 'polycc[crazyflie]' (or pip install "
                          "'cflib>=0.1.32')") from None
    if SerialDriver not in cflib.crtp.CLASSES:  # init_drivers appends the drivers again on every call
        cflib.crtp.init_drivers(enable_serial_driver=True)
    scf = SyncCrazyflie(uri, cf=Crazyflie(rw_cache=rw_cache))
    result: dict = {}

    def run():
        try:
            scf.open_link()
            scf.wait_for_params()
            result["ok"] = True
        except BaseException as e:  # noqa: BLE001 - reported below
            result["error"] = e

    t = threading.Thread(target=run, name="cflib-connect", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive() or "error" in result:
        try:
            close_without_stop(scf)
        except Exception:
            pass
        if "error" in result:
            raise PolyccError(f"cflib could not connect to {uri}: {_one_line(result['error'])}")
        raise _Stalled(f"cflib could not connect to {uri}: no TOC and param values within {timeout_s:g} s")
    return scf
