"""The committed store of real-firmware bench flights (bench/flight_store.py, bench/flights/) reads back
clean: names, fields, series and their recorded jerk RMS agree. bench/ is not importable from tests, so
the store's own check runs as a process, on the committed cells and on a cell this test writes wrong."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

from polycc.testing.files import CHECKOUT

STORE = CHECKOUT / "bench" / "flights" / "shield_firmware"
SCRIPT = CHECKOUT / "bench" / "flight_store.py"


def _check(root=None):
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import flight_store as fs; "
            "from pathlib import Path; p = fs.check(Path(sys.argv[2])) if len(sys.argv) > 2 else fs.check(); "
            "print('\\n'.join(p)); raise SystemExit(1 if p else 0)")
    args = [sys.executable, "-c", code, str(SCRIPT.parent)] + ([str(root)] if root else [])
    return subprocess.run(args, capture_output=True, text=True, timeout=120)


def test_the_committed_flights_read_back_clean():
    r = subprocess.run([sys.executable, str(SCRIPT), "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "0 problems" in r.stdout


def test_a_damaged_cell_is_reported(tmp_path):
    cells = sorted(STORE.glob("*.json"))
    assert cells, f"no committed cells in {STORE}"
    good = tmp_path / cells[0].name
    shutil.copy(cells[0], good)
    assert _check(tmp_path).returncode == 0
    data = json.loads(good.read_text())
    k = next(iter(data["flights"]))
    data["flights"][k]["jerk_rms"] *= 1.5  # a record that does not match its series, in a misnamed cell
    (tmp_path / good.name.replace(f"_{data['mode']}_", "_other_")).write_text(json.dumps(data))
    del data["flights"][k]["gap"]  # a record without a field the rows read
    good.write_text(json.dumps(data))
    r = _check(tmp_path)
    assert r.returncode == 1
    assert "no ['gap']" in r.stdout and "head says" in r.stdout and "jerk RMS" in r.stdout, r.stdout
