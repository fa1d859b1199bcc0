"""Shared test fixtures and helpers."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from polycc.testing.files import SCENES  # noqa: E402 - ../shared/scenes beside the checkout

# Hypothesis: deterministic in CI, no deadline (shared, noisy machines).
try:
    from hypothesis import HealthCheck, settings

    settings.register_profile("polycc", deadline=None, suppress_health_check=[HealthCheck.too_slow],
                              derandomize=bool(os.environ.get("CI")))
    settings.load_profile("polycc")
except ImportError:  # pragma: no cover
    pass


def pytest_configure(config):
    """Tests stop `polycc sim-device` & co. with SIGINT, as Ctrl-C in a terminal does. A suite started in the
    background (``make test &``, nohup, some CI runners) inherits SIGINT ignored, every child it spawns would
    too, and Python then never raises KeyboardInterrupt: the device would not stop. Run as a foreground
    terminal would (runs in the main process and in every xdist worker)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def scenes_dir() -> Path:
    if not SCENES.is_dir():
        pytest.skip(f"real scenes not found at {SCENES} (clone with ../shared beside the repo)")
    return SCENES


# The modules with the longest tests (CI's --durations of 2026-12-06), longest first. Collected first, so
# pytest-xdist hands them out at the start and the many short tests fill both workers at the end: in
# collection order the 4-drone swarm (170-245 s) ended at about 93% of the suite and could leave the other
# worker idle. Each module keeps its own order (its module fixtures are set up once per worker, as before).
LONG_FIRST = ("tests/sim/test_swarm_firmware.py", "tests/sim/test_firmware_sitl.py",
              "tests/onboard/test_kernel_index.py", "tests/ground/test_flash_upstream.py", "tests/test_install.py",
              "tests/cover/test_cover_scenes.py", "tests/onboard/test_shield.py")


def pytest_collection_modifyitems(session, config, items):
    def rank(item):
        path = Path(str(item.fspath)).resolve().relative_to(Path(__file__).resolve().parent.parent).as_posix()
        return LONG_FIRST.index(path) if path in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: the collection order within each rank
