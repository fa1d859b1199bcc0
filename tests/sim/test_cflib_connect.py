"""Bitcraze's real cflib connects to the simulated Crazyflie over UDP and over a serial pty.

cflib's serial driver only opens a NAME listed by pyserial's ``comports()``. On Linux that scans
``/dev/ttyUSB*`` (and similar globs), so :class:`SerialDeviceServer` creates the symlink
``/dev/ttyUSB-polycc...`` -> ``/dev/pts/N``, which needs root (as in CI). Without root the test
patches ``SerialDriver.get_devices`` instead: that is the one thing the symlink provides, and
everything below it (pyserial on the pty, CPX framing, the FF 00 handshake) is still real.
Both ways run when root is available.
"""

from __future__ import annotations

import itertools
import os
from contextlib import ExitStack
from unittest import mock

import pytest

from polycc.sim.crtp_device import CrtpDevice
from polycc.sim.device_server import SerialDeviceServer, UdpDeviceServer
from polycc.testing.cflib_session import run_with_timeout, scenario
from polycc.testing.link_fake_model import FakeModel

cflib_crtp = pytest.importorskip("cflib.crtp", reason="cflib is not installed (pip install 'polycc[crazyflie]')")
from cflib.crtp.serialdriver import SerialDriver  # noqa: E402

_names = itertools.count()


@pytest.fixture(scope="module", autouse=True)
def drivers():
    if SerialDriver not in cflib_crtp.CLASSES:  # init_drivers appends on every call
        cflib_crtp.init_drivers(enable_serial_driver=True)


def check(out: dict, model: FakeModel) -> None:
    assert out["log_toc"] == {e.full_name for e in model.logs}
    assert out["param_toc"] == {e.full_name for e in model.params} | {"firmware.polyccVersion"}
    assert float(out["goalX_initial"]) == 0.0
    assert float(out["goalX_read"]) == 2.5 and out["goalX_model"] == 2.5
    assert [d for _, d in out["log"]] == [{"polycc.psi": 0.25, "stateEstimate.x": 1.5}] * 5
    stamps = [ts for ts, _ in out["log"]]
    assert all(b - a == 10 for a, b in zip(stamps, stamps[1:])), stamps
    assert out["app"] == [b"ack:hello"] and model.app_rx == [b"hello"]


def test_cflib_connects_over_udp():
    model = FakeModel()
    with UdpDeviceServer(CrtpDevice(model), port=0) as srv:
        out = run_with_timeout(lambda: scenario(srv.uri, model))
        assert srv.bad_datagrams == 0
    check(out, model)
    assert out["connect_s"] < 2.0


@pytest.mark.parametrize("discovery", ["comports", "patched"])
def test_cflib_connects_over_serial_pty_twice(discovery):
    model = FakeModel()
    name = f"ttyUSB-polycc-t{os.getpid()}-{next(_names)}"  # unique under pytest -n
    with ExitStack() as stack:
        link_name = name if discovery == "comports" else ""  # "": no symlink
        srv = stack.enter_context(SerialDeviceServer(CrtpDevice(model), link_name=link_name))
        if discovery == "comports":
            if srv.link_path is None:
                pytest.skip("cannot create the /dev symlink comports() would list (needs root)")
            import serial.tools.list_ports as list_ports

            assert name in {p.name for p in list_ports.comports()}  # what cflib's get_devices scans
            uri = srv.uri
        else:
            # Without root /dev is not writable, so comports() cannot list the pty. Patch the one
            # lookup the symlink would have satisfied; the serial I/O below stays real.
            name = os.path.basename(srv.pty_path)
            stack.enter_context(mock.patch.object(SerialDriver, "get_devices", lambda self: {name: srv.pty_path}))
            uri = f"serial://{name}"
        out = run_with_timeout(lambda: scenario(uri, model))
        check(out, model)
        # a second session on the same pty: the device notices the hang-up and handshakes again
        model.app_rx.clear()
        model.values["polycc.goalX"] = 0.0
        out = run_with_timeout(lambda: scenario(uri, model))
        check(out, model)
        assert srv.hangups >= 1 and srv.link.decoder.stats.errors == 0
    assert srv.link_path is None or not os.path.lexists(srv.link_path)  # symlink removed on stop
