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


@pytest.fixture(scope="session")
def demo_build(tmp_path_factory, worker_id):
    """``copy(dest) -> dest``: the demo arena (``arena.ply``, ``arena.json``) and its build ``b/``
    (``polycc build arena.ply --flash-kb 8 --mc-samples 5000``) copied into the folder ``dest``. Built
    once per test run and shared by the xdist workers (a file lock), since ten tests fly that same header."""
    import fcntl
    import shutil

    from polycc.cli import main

    root = tmp_path_factory.getbasetemp()
    if worker_id != "master":  # every worker's basetemp is a sibling under the run's own folder
        root = root.parent
    src = root / "demo_build_8kb"
    with open(root / "demo_build_8kb.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (src / "done").is_file():
            shutil.rmtree(src, ignore_errors=True)
            src.mkdir()
            assert main(["demo-scene", str(src / "arena.ply")]) == 0
            assert main(["build", str(src / "arena.ply"), "--flash-kb", "8", "--mc-samples", "5000",
                         "-o", str(src / "b")]) == 0
            (src / "done").write_text("")
        fcntl.flock(lock, fcntl.LOCK_UN)

    def copy(dest):
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        for name in ("arena.ply", "arena.json"):
            shutil.copy2(src / name, dest / name)
        shutil.copytree(src / "b", dest / "b")
        return dest

    return copy
