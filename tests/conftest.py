"""Shared test fixtures and helpers."""

from __future__ import annotations

import os
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


@pytest.fixture
def scenes_dir() -> Path:
    if not SCENES.is_dir():
        pytest.skip(f"real scenes not found at {SCENES} (clone with ../shared beside the repo)")
    return SCENES
