"""`pip install .` (a wheel, not an editable checkout) works from another folder: build, verify, sim,
sim-device and flash --dry-run, with the C sources, templates and shims taken from the wheel."""

from __future__ import annotations

import os
import site
import subprocess
import sys
import sysconfig

import pytest

from polycc.testing.files import CHECKOUT


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    wheels = tmp_path / "wheels"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                        str(wheels), str(CHECKOUT)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = wheels.glob("polycc-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    # the wheel alone, its dependencies from this environment (no network, no editable finder)
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    deps = [p for p in site.getsitepackages() + [sysconfig.get_paths()["purelib"]] if os.path.isdir(p)]
    (tmp_path / "venv" / "deps.pth").write_text("\n".join(deps) + "\n")
    os.replace(tmp_path / "venv" / "deps.pth", os.path.join(purelib, "zz_deps.pth"))
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = dict(os.environ, POLYCC_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("PYTHONPATH", None)
    polycc = [str(py), "-m", "polycc"]

    def run(*args, ok=(0,)):
        r = subprocess.run([*polycc, *args], cwd=work, env=env, capture_output=True, text=True)
        assert r.returncode in ok, f"polycc {' '.join(args)}: {r.stdout[-2000:]}{r.stderr[-2000:]}"
        return r.stdout

    where = subprocess.run([str(py), "-c", "import polycc, polycc.resources as r; print(polycc.__file__); "
                            "print(r.firmware_app())"], cwd=work, env=env, capture_output=True, text=True, check=True)
    assert str(CHECKOUT) not in where.stdout, where.stdout  # the installed copy, not the checkout
    run("demo-scene", "arena.ply")
    run("build", "arena.ply", "--flash-kb", "4", "--mc-samples", "5000", "-o", "b")
    assert "PASS" in run("verify", "b", "arena.ply", "--min-samples", "50000", "--mc-samples", "5000")
    assert "collisions: 0" in run("sim", "b", "--dynamics", "integrator", "--t-max", "5", ok=(0, 1))
    assert "URI: udp://" in run("sim-device", "b", "--udp", "127.0.0.1:0", "--duration", "0.5")
    assert "step 1: copy firmware_app/" in run("flash", "b", "--crazyflie-base", str(tmp_path), "--dry-run", ok=(0, 2))
    assert (tmp_path / "cache" / "cffi").is_dir()  # builds went to the user cache
    # the cover's counts and the budget's drop volumes ran in C from the wheel's polycc/native/, not the numpy fallback
    built = sorted(p.name for p in (tmp_path / "cache" / "cffi").iterdir())
    assert any(b.startswith("_polycc_native_") for b in built), built
    # the real-firmware SITL's C support files ship in the wheel
    subprocess.run([str(py), "-c", "from polycc.sim.firmware.build import CLOCK_SHIM_SOURCE as a, FIXES_SOURCE as b; "
                    "assert a.is_file() and b.is_file(), (a, b)"], cwd=work, env=env, check=True)
