"""The committed store of real-firmware bench flights (bench/flights/): one JSON file per cell.

A real-firmware SITL flight takes 20-40 s of wall time and cannot share the host with another (a loaded
host starves the app task, which changes the flight), so the 100 pairs per speed of issue 18 take hours.
They accumulate here, in git, across runs and machines:

* a cell is one (store key, mode, commanded speed); its file holds one record per pair number;
* the store key is the cf2 build key (app sources, header, kconfig, flags, compiler) joined with a hash of
  the flight code (polycc/sim/firmware/*.py but build.py, whose inputs the cf2 key holds) and of the
  flight's FlightConfig, so flights of another build or procedure are never mixed in;
* a record keeps its start and goal, and is used only for the same pair;
* the per-sample series (jerk of the truth at 100 Hz, m/s^3; barrier-rate gap at 50 Hz, m/s) are kept as
  zlib-compressed float16 (float32 if a value is beyond float16's range), base64 in the JSON: about
  2-3 KB per flight.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import zlib
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
STORE = REPO / "bench" / "flights" / "shield_firmware"
FLIGHT_CODE = REPO / "polycc" / "sim" / "firmware"
F16_MAX = 60000.0


def encode(a) -> dict:
    """A float series as {"dtype", "n", "z"} (zlib + base64 of its float16, or float32, bytes)."""
    a = np.asarray(a, np.float64).ravel()
    dt = "<f2" if (not len(a) or np.nanmax(np.abs(a)) < F16_MAX) else "<f4"
    raw = a.astype(dt).tobytes()
    return {"dtype": dt, "n": int(len(a)), "z": base64.b64encode(zlib.compress(raw, 9)).decode("ascii")}


def decode(d: dict) -> np.ndarray:
    """The float64 series of :func:`encode`."""
    raw = zlib.decompress(base64.b64decode(d["z"]))
    a = np.frombuffer(raw, d["dtype"]).astype(np.float64)
    if len(a) != d["n"]:
        raise ValueError(f"flight store: series of {len(a)} values, {d['n']} recorded")
    return a


def code_hash() -> str:
    """sha256 of the flight code: every .py in polycc/sim/firmware but build.py (the cf2 key covers it)."""
    h = hashlib.sha256()
    for p in sorted(FLIGHT_CODE.glob("*.py")):
        if p.name != "build.py":
            h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def store_key(cf2_key: str, cfg) -> str:
    """The cell key: cf2 build key (16 hex) + flight code and FlightConfig (8 hex)."""
    cfg_json = json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str)
    h = hashlib.sha256((code_hash() + cfg_json).encode()).hexdigest()
    return f"{cf2_key[:16]}-{h[:8]}"


class Cell:
    """One cell's file: ``get(k, start, goal)`` a stored record or None, ``put(k, rec)`` writes it at once."""

    def __init__(self, key: str, mode: str, speed: float, root: Path = STORE):
        self.path = Path(root) / f"{key}_{mode}_{speed:g}ms.json"
        self.head = {"key": key, "mode": mode, "speed": float(speed)}
        self.flights: dict[str, dict] = {}
        if self.path.is_file():
            data = json.loads(self.path.read_text())
            if {k: data.get(k) for k in self.head} != self.head:
                raise ValueError(f"{self.path}: its head {({k: data.get(k) for k in self.head})} is not {self.head}")
            self.flights = data["flights"]

    def get(self, k: int, start, goal) -> dict | None:
        rec = self.flights.get(str(k))
        if rec is None:
            return None
        if not (np.allclose(rec["start"], start, atol=1e-9) and np.allclose(rec["goal"], goal, atol=1e-9)):
            return None  # another pair under this number (the pairs' seed or count changed): fly it again
        return rec

    def put(self, k: int, rec: dict) -> None:
        self.flights[str(k)] = rec
        self.path.parent.mkdir(parents=True, exist_ok=True)
        body = {**self.head, "flights": {key: self.flights[key] for key in sorted(self.flights, key=int)}}
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps(body, indent=1, sort_keys=False) + "\n")
        tmp.replace(self.path)


FIELDS = {"start", "goal", "outcome", "success", "time_s", "collisions", "min_clearance_m", "shield", "landed",
          "sitl_reruns", "rtf", "wall_s", "jerk_rms", "jerk", "gap"}


def check(root: Path = STORE) -> list[str]:
    """Every committed cell, read back: its name matches its head, every record has the fields the rows
    read, its series decode to their recorded length, its jerk RMS is that of its series (float16
    rounding) and its start and goal are finite 3-vectors. Returns the problems found (empty: clean)."""
    problems = []
    for path in sorted(Path(root).glob("*.json")):
        try:
            data = json.loads(path.read_text())
            key, mode, speed = data["key"], data["mode"], data["speed"]
            if path.name != f"{key}_{mode}_{float(speed):g}ms.json":
                problems.append(f"{path.name}: head says {key}, {mode}, {speed} m/s")
            for k, rec in data["flights"].items():
                where = f"{path.name} pair {k}"
                missing = FIELDS - set(rec)
                if missing:
                    problems.append(f"{where}: no {sorted(missing)}")
                    continue
                jerk = decode(rec["jerk"])
                decode(rec["gap"])
                rms = float(np.sqrt(np.mean(jerk ** 2))) if len(jerk) else float("nan")
                if not (np.isnan(rms) and np.isnan(rec["jerk_rms"])) and not np.isclose(rms, rec["jerk_rms"],
                                                                                         rtol=2e-3):
                    problems.append(f"{where}: jerk RMS {rec['jerk_rms']} recorded, {rms} in its series")
                for name in ("start", "goal"):
                    v = np.asarray(rec[name], float)
                    if v.shape != (3,) or not np.isfinite(v).all():
                        problems.append(f"{where}: {name} {rec[name]}")
        except (OSError, ValueError, KeyError, TypeError, zlib.error) as exc:
            problems.append(f"{path.name}: {type(exc).__name__}: {exc}")
    return problems


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--check"]:
        raise SystemExit("usage: python bench/flight_store.py --check   (reads every committed cell back)")
    found = check()
    for line in found:
        print(line)
    n = sum(len(json.loads(p.read_text())["flights"]) for p in STORE.glob("*.json")) if STORE.is_dir() else 0
    print(f"flight store {STORE}: {len(list(STORE.glob('*.json')))} cells, {n} flights, {len(found)} problems")
    raise SystemExit(1 if found else 0)
