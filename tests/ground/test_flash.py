"""`polycc flash`: the dry run prints every step, and errors name the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from polycc.cli import main
from polycc.codegen.header import write_outputs
from polycc.geometry.halfplanes import axis_box


@pytest.fixture(scope="module")
def walls(tmp_path_factory):
    d = tmp_path_factory.mktemp("flash")
    write_outputs(d, [axis_box([0, 0, 0], [1, 1, 1])], {"kappa": 100.0})
    return d, None


def _fake_firmware(root: Path, git: bool = False) -> Path:
    (root / "tools" / "make").mkdir(parents=True)
    (root / "tools" / "make" / "oot.mk").write_text("all:\n")
    (root / "vendor" / "FreeRTOS" / "include").mkdir(parents=True)
    (root / "vendor" / "FreeRTOS" / "include" / "FreeRTOS.h").write_text("")
    (root / "vendor" / "CMSIS" / "CMSIS" / "Core" / "Include").mkdir(parents=True)
    (root / "vendor" / "libdw1000" / "inc").mkdir(parents=True)
    if git:
        (root / ".git").mkdir()
    return root


def test_flash_dry_run_prints_every_step(walls, tmp_path, capsys):
    d, _ = walls
    base = _fake_firmware(tmp_path / "cf")
    rc = main(["flash", str(d), "--crazyflie-base", str(base), "--dry-run", "--no-flash", "--build-dir",
               str(tmp_path / "b")])
    out = capsys.readouterr().out
    assert "step 1: copy firmware_app/" in out and "build_info.json" in out
    assert "CRAZYFLIE_BASE=" in out and "arm-none-eabi-size" in out
    assert not (tmp_path / "b").exists()  # nothing was run
    assert rc in (0, 2)  # 2 only if this machine lacks the ARM toolchain
    rc = main(["flash", str(d), "--crazyflie-base", str(base), "--dry-run", "--build-dir", str(tmp_path / "b")])
    out = capsys.readouterr().out
    assert "cfloader flash" in out and "stm32-fw -w radio://0/80/2M/E7E7E7E7E7" in out


def test_flash_errors_are_clear(walls, tmp_path, capsys, monkeypatch):
    d, _ = walls
    assert main(["flash", str(d), "--crazyflie-base", str(tmp_path / "nowhere")]) == 2
    assert "no crazyflie-firmware tree" in capsys.readouterr().err
    base = _fake_firmware(tmp_path / "cf")
    (base / "vendor" / "libdw1000" / "inc").rmdir()
    assert main(["flash", str(d), "--crazyflie-base", str(base)]) == 2
    assert "git submodule update --init --recursive" in capsys.readouterr().err
    (base / "vendor" / "libdw1000" / "inc").mkdir()
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert main(["flash", str(d), "--crazyflie-base", str(base)]) == 2
    assert "no ARM toolchain" in capsys.readouterr().err


def test_copy_app_refreshes_an_older_header_in_a_reused_build_folder(tmp_path):
    """Regression: copy2 kept the new header's (older) mtime, so make kept the previous scene's objects
    and a reused build folder flashed the OLD obstacles (found by the 16/64 KiB build of the issue-13 bench)."""
    import os

    from polycc.ground.flash import copy_app

    a, b, app = tmp_path / "a", tmp_path / "b", tmp_path / "fw" / "polycc_app"
    for d, text in ((a, "/* scene A */\n"), (b, "/* scene B */\n")):
        d.mkdir()
        (d / "polytopes.h").write_text(text)
    os.utime(b / "polytopes.h", (1_000_000, 1_000_000))  # B is older than everything
    copy_app(a, app, tmp_path)
    obj = app / "src" / "polycc_app.o"
    obj.write_text("built from A")
    t_obj = obj.stat().st_mtime
    copy_app(b, app, tmp_path)
    assert (app / "polytopes.h").read_text() == "/* scene B */\n"
    assert (app / "polytopes.h").stat().st_mtime >= t_obj  # make sees the header as newer than the object
    m = (app / "polytopes.h").stat().st_mtime_ns
    copy_app(b, app, tmp_path)  # same bytes: left alone, nothing rebuilds
    assert (app / "polytopes.h").stat().st_mtime_ns == m
