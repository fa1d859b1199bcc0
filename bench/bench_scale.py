"""Benchmark: `polycc build --flash-kb 64` at finer voxels and on bigger scenes, today's code beside ours.

For each case (the tiled benchmark room of real captures, `polycc.demo.arenas.tiled_room`, at a
splat count and voxel size g) the same command runs twice in one run of this script:

* baseline: the base commit of this work (BASE_COMMIT), exported once into build/baseline with
  `git archive` and run from there (PYTHONPATH), as `python -m polycc build ...`;
* ours: this checkout, `polycc build ... --jobs J` (default: every core).

Measured per run: wall seconds, the stage times it prints (occupancy / cover / budget), CPU
seconds and peak RSS of the whole process tree (psutil, sampled every 0.2 s: the sum over the main
process and its workers, each process's CPU counted once), n, bytes, the conservativeness with its
95 % interval; our result must pass `polycc verify` (the stored polytopes as the C decodes them,
every voxel and splat samples). Then: the growth of the build time from 5 to 2.5 cm, `--dask local:1` against
`--dask local:2` on the 2.5 cm case, and a projection of the 15M-splat, 1 cm case from the
measured task costs per kd depth (cover.npz meta).

    python bench/bench_scale.py [--quick] [--cases room1.5M_5,...] [--no-baseline] [--resume]

--quick runs the 150k-splat room only. Results go to bench/results/scale.json (per case as it
finishes; --resume skips cases already there).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import CACHE, REPO, RESULTS, print_table, write_json  # noqa: E402

BASE_COMMIT = "aa94c51"
BASELINE = REPO / "build" / "baseline"
CASES = {  # name: (splats, voxel m)
    "room150k_5": (150_000, 0.05), "room150k_25": (150_000, 0.025),
    "room1.5M_5": (1_500_000, 0.05), "room1.5M_25": (1_500_000, 0.025),
    "room6M_5": (6_000_000, 0.05),
}
QUICK = ("room150k_5", "room150k_25")
TARGETS = {"room1.5M_5": "<= 45 s", "room1.5M_25": "<= 120 s", "room6M_5": "<= 90 s, <= 4 GB"}


def baseline_checkout() -> Path:
    """build/baseline = the tree of BASE_COMMIT (made once; no git metadata is touched)."""
    if not (BASELINE / "polycc" / "__init__.py").is_file():
        BASELINE.mkdir(parents=True, exist_ok=True)
        arch = subprocess.run(["git", "-C", str(REPO), "archive", BASE_COMMIT], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(BASELINE)], input=arch, check=True)
    return BASELINE


def room(splats: int) -> Path:
    from bench_occupancy import room_ply

    return Path(room_ply(splats))


def run_tree(cmd: list[str], env: dict, log: Path) -> dict:
    """Run cmd; wall s, CPU s and peak RSS (GB) of its process tree, exit code, stdout.

    Sampled every 0.2 s (psutil) over the main process and every descendant: peak RSS is the largest sum,
    CPU seconds the sum over processes of each one's own user + system time at its last sample (a process's
    CPU after its last sample is lost: at most 0.2 s of each). Regression: a process's reaped children's
    times were added to its own, so a worker forked by the build (the selection forks a pool per stage) was
    counted twice, once under its own pid and again in its parent's; the kernel's account of reaped children
    (``getrusage``, or the shell's ``time``) is no substitute: it misses the forkserver pool's workers, which
    the build never reaps itself (the shell's ``time`` read the 6M-splat room's build as 95 CPU s in 111 s,
    where /proc/stat had both cores busy 1.85 of 2 on average)."""
    import psutil

    t0 = time.perf_counter()
    with open(log, "w") as out:
        p = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd="/tmp")
        root = psutil.Process(p.pid)
        peak, cpu = 0, {}
        while p.poll() is None:
            try:
                rss = 0
                for q in [root] + root.children(recursive=True):
                    try:
                        rss += q.memory_info().rss
                        t = q.cpu_times()
                        cpu[(q.pid, q.create_time())] = t.user + t.system
                    except psutil.Error:
                        pass
                peak = max(peak, rss)
            except psutil.Error:
                pass
            time.sleep(0.2)
    wall = time.perf_counter() - t0
    used = sum(cpu.values())
    return {"wall_s": wall, "cpu_s": used, "busy_cores": used / max(wall, 1e-9), "peak_rss_gb": peak / 2**30,
            "rc": p.returncode, "out": log.read_text(errors="replace")}


def parse_summary(text: str) -> dict:
    """Stage times and n from the build summary both versions print."""
    out = {}
    m = re.search(r"time: occupancy / cover / budget\s*│\s*([\d.]+) / ([\d.]+) / ([\d.]+) s", text)
    if m:
        out["occupancy_s"], out["cover_s"], out["budget_s"] = (float(x) for x in m.groups())
    m = re.search(r"voxels \(g\)\s*│\s*([\d,]+)", text)
    if m:
        out["voxels"] = int(m.group(1).replace(",", ""))
    return out


def build(which: str, ply: Path, g: float, out: Path, extra: list[str]) -> dict:
    env = dict(os.environ)
    env["POLYCC_CACHE_DIR"] = str(REPO / ".cache-polycc")
    if which == "baseline":
        env["PYTHONPATH"] = str(baseline_checkout())
    cmd = [sys.executable, "-m", "polycc", "build", str(ply), "--voxel", str(g), "--flash-kb", "64", "-o", str(out),
           *extra]
    r = run_tree(cmd, env, out.parent / f"{out.name}.log")  # (with_suffix would cut "room1.5M_5" at its dot)
    r.update(parse_summary(r["out"]))
    if r["rc"] == 0:
        st = json.loads((out / "manifest.json").read_text())["stats"]
        r.update(n=st["n"], bytes=st["bytes"], conservativeness=st["conservativeness"],
                 ci95=st["conservativeness_ci95"], n_subcover=st["n_subcover"], voxels=st["voxels"])
        if which == "ours":
            import numpy as np

            with np.load(out / "cover.npz") as z:
                r["cover_meta"] = json.loads(str(z["meta"]))
    r["tail"] = "\n".join(r.pop("out").strip().splitlines()[-3:])
    return r


def verify(out: Path, scene: Path) -> dict:
    env = dict(os.environ, POLYCC_CACHE_DIR=str(REPO / ".cache-polycc"))
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "polycc", "verify", str(out), str(scene)], capture_output=True,
                       text=True, env=env, cwd="/tmp")
    last = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else p.stderr.strip()[-300:]
    return {"ok": p.returncode == 0 and last.startswith("verify: PASS"), "line": last, "s": time.perf_counter() - t}


def projection(r25: dict, r5: dict | None, splats: float = 15e6, g: float = 0.01, workers=(2, 16, 64)) -> dict:
    """Paper estimate of the 15M-splat, 1 cm build from the measured 1.5M, 2.5 cm run: voxels
    scale with the splat count (more copies of the captures) and with 1/g^2 (surfaces); the
    tiles' work per voxel is measured; the kd depth grows by log2 of the voxel ratio with the
    same per-level work at the inner levels (each level halves the nodes of the one below), and
    the root stage's work (a fixed ~root_nodes) grows with its nodes' area, 1/g^2."""
    meta = r25["cover_meta"]["tiles"]
    V0 = r25["voxels"]
    scale_v = (splats / 1.5e6) * (0.025 / g) ** 2
    V = V0 * scale_v
    depth = meta["by_depth"]
    D = max(int(k) for k in depth)
    leaf = {k: v for k, v in depth.items() if int(k) >= D - 1}  # tiles sit at the two deepest levels
    tile_s_per_voxel = sum(v["seconds"] for v in leaf.values()) / max(1, sum(v["voxels"] for v in leaf.values()))
    inner = [v["seconds"] for k, v in depth.items() if 0 < int(k) < D - 1]
    per_level = (sum(inner) / len(inner)) if inner else depth.get("1", {"seconds": 0.0})["seconds"]
    levels_new = D + math.log2(scale_v)
    root = depth["0"]["seconds"] * (0.025 / g) ** 2
    tiles_s = tile_s_per_voxel * V
    inner_s = per_level * (levels_new - 1) * (0.025 / g) ** 2
    tiles = V / meta["tile_voxels"]
    rows = []
    for w in workers:
        # inner levels: level d has 2^d tasks; the top ones cannot use all workers
        level_s = per_level * (0.025 / g) ** 2
        wall = tiles_s / w + sum(level_s / min(w, 2**d) for d in range(1, int(levels_new))) + root
        rows.append({"workers": w, "cover_wall_s": wall})
    return {"splats": splats, "g": g, "voxels": V, "tiles": tiles, "tile_task_s_per_voxel": tile_s_per_voxel,
            "tiles_cpu_s": tiles_s, "inner_levels_cpu_s": inner_s, "root_s": root, "kd_levels": levels_new,
            "by_workers": rows,
            "memory": {"per_tile_worker_gb": meta["tile_voxels"] * 150 / 2**30 + 0.25,
                       "root_gb": V * (24 + 24 + 8) / 2**30 + 0.5, "client_gb": V * 48 / 2**30 + splats * 150 / 2**30}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the 150k-splat room only")
    ap.add_argument("--cases", default=None, help=f"comma list of {', '.join(CASES)}")
    ap.add_argument("--no-baseline", action="store_true", help="only our code")
    ap.add_argument("--no-dask", action="store_true", help="skip the --dask local:1 / local:2 runs")
    ap.add_argument("--jobs", type=int, default=None, help="--jobs for our builds (default: every core)")
    ap.add_argument("--resume", action="store_true", help="keep the cases already in bench/results/scale.json")
    args = ap.parse_args()
    names = args.cases.split(",") if args.cases else list(QUICK if args.quick else CASES)
    path = RESULTS / "scale.json"
    res = json.loads(path.read_text()).get("cases", {}) if args.resume and path.exists() else {}
    extra = [] if args.jobs is None else ["--jobs", str(args.jobs)]
    outdir = CACHE / "scale"
    outdir.mkdir(parents=True, exist_ok=True)
    dask_case = "room1.5M_25" if "room1.5M_25" in names else names[-1]
    for name in names:
        if name in res:
            continue
        splats, g = CASES[name]
        ply = room(splats)
        case = {"splats": splats, "g": g, "load_average_at_start": os.getloadavg()[0]}
        if not args.no_baseline:
            case["baseline"] = build("baseline", ply, g, outdir / f"{name}_base", [])
            print(f"{name} baseline: {case['baseline']['wall_s']:.1f} s", flush=True)
        case["ours"] = build("ours", ply, g, outdir / f"{name}_ours", extra)
        print(f"{name} ours: {case['ours']['wall_s']:.1f} s", flush=True)
        if case["ours"]["rc"] == 0:
            case["verify"] = verify(outdir / f"{name}_ours", ply)
            print(f"  {case['verify']['line']}", flush=True)
        if name == dask_case and not args.no_dask:
            for w in (1, 2):
                case[f"dask{w}"] = build("ours", ply, g, outdir / f"{name}_dask{w}", ["--dask", f"local:{w}"])
                print(f"  dask local:{w}: {case[f'dask{w}']['wall_s']:.1f} s", flush=True)
        res[name] = case
        write_json("scale", {"cases": res})
    report(res)


def fmt_run(r: dict | None) -> list:
    if not r:
        return ["-"] * 6
    if r.get("rc"):
        return [f"failed ({r['tail'][-60:]})"] + ["-"] * 5
    stages = f"{r.get('occupancy_s', 0):.1f} / {r.get('cover_s', 0):.1f} / {r.get('budget_s', 0):.1f}"
    return [round(r["wall_s"], 1), stages, round(r["cpu_s"], 0), round(r["peak_rss_gb"], 2), r.get("n"),
            f"{r.get('conservativeness', float('nan')):.4f} ± {r.get('ci95', float('nan')):.4f}"]


def report(res: dict) -> None:
    rows = []
    for name, c in res.items():
        b, o = c.get("baseline"), c["ours"]
        speed = f"{b['wall_s'] / o['wall_s']:.2f}x" if b and not b.get("rc") and not o.get("rc") else "-"
        rows.append([name, f"{c['splats']:,}", f"{c['g'] * 100:g} cm", o.get("voxels", "-"), *fmt_run(b),
                     *fmt_run(o), speed, c.get("verify", {}).get("ok", "-"), TARGETS.get(name, "")])
    print_table("polycc build --flash-kb 64 on the tiled room: baseline (" + BASE_COMMIT + ") | ours, one run "
                "(wall s; stages occupancy / cover / budget s; CPU s and peak RSS GB of the process tree)",
                ["case", "splats", "g", "voxels", "base wall", "base stages", "base CPU", "base GB", "base n",
                 "base cons.", "ours wall", "ours stages", "ours CPU", "ours GB", "ours n", "ours cons.",
                 "speed-up", "verify", "target"], rows)
    growth = []
    for size in ("150k", "1.5M"):
        a, b = res.get(f"room{size}_5"), res.get(f"room{size}_25")
        if a and b:
            for who in ("baseline", "ours"):
                if a.get(who) and b.get(who) and not a[who].get("rc") and not b[who].get("rc"):
                    growth.append([size, who, f"{b[who]['wall_s'] / a[who]['wall_s']:.2f}x",
                                   f"{b[who]['cpu_s'] / max(a[who]['cpu_s'], 1e-9):.2f}x",
                                   f"{b[who]['voxels'] / a[who]['voxels']:.2f}x", "<= 4.5x" if who == "ours" else ""])
    if growth:
        print_table("cost growth 5 -> 2.5 cm (wall, CPU) against the voxel count", ["room", "code", "wall", "CPU",
                                                                                   "voxels", "target"], growth)
    for name, c in res.items():
        if "dask1" in c and "dask2" in c and not c["dask1"].get("rc") and not c["dask2"].get("rc"):
            d1, d2 = c["dask1"], c["dask2"]
            print_table(f"{name}: Dask local cluster, 1 worker against 2 (target >= 1.7x)",
                        ["workers", "wall s", "cover s", "CPU s", "peak GB", "cons."],
                        [[1, round(d1["wall_s"], 1), d1.get("cover_s"), round(d1["cpu_s"]), round(d1["peak_rss_gb"], 2),
                          f"{d1['conservativeness']:.4f}"],
                         [2, round(d2["wall_s"], 1), d2.get("cover_s"), round(d2["cpu_s"]), round(d2["peak_rss_gb"], 2),
                          f"{d2['conservativeness']:.4f}"],
                         ["speed-up", f"{d1['wall_s'] / d2['wall_s']:.2f}x",
                          f"{d1['cover_s'] / d2['cover_s']:.2f}x" if d1.get("cover_s") and d2.get("cover_s") else "-",
                          "", "", ""]])
    r25 = res.get("room1.5M_25", {}).get("ours")
    if r25 and not r25.get("rc"):
        p = projection(r25, res.get("room1.5M_5", {}).get("ours"))
        print_table(f"projection, {p['splats'] / 1e6:g}M splats at {p['g'] * 100:g} cm, from the measured 1.5M / "
                    f"2.5 cm task costs: {p['voxels'] / 1e6:.1f}M voxels, {p['tiles']:,.0f} tiles, "
                    f"{p['kd_levels']:.1f} kd levels, tile work {p['tiles_cpu_s'] / 3600:.1f} CPU h, "
                    f"root stage {p['root_s']:.0f} s",
                    ["workers", "cover wall (h)"], [[w["workers"], round(w["cover_wall_s"] / 3600, 2)]
                                                    for w in p["by_workers"]])
        print("memory:", {k: round(v, 2) for k, v in p["memory"].items()}, "GB")
        write_json("scale", {"cases": res, "projection_15M_1cm": p})


if __name__ == "__main__":
    main()
