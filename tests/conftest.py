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
