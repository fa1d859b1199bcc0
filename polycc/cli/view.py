"""`polycc view DIR`: a browser view of the splats, the stored cover, the chosen n and flights from `polycc sim`."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from polycc import pipeline
from polycc.cli.argtypes import number
from polycc.cli.console import StageProgress, console, warn
from polycc.cli.scene_args import check_scene_file, recorded_settings
from polycc.errors import PolyccError
from polycc.view.viewer import MAX_SPLATS, content_for, start


def register(sub) -> None:
    p = sub.add_parser(
        "view",
        help="open a browser view of a build: splats, stored polytopes, chosen n, flights from `polycc sim`",
        description="Serve a 3D view (viser, in the browser) of DIR: the scene's splats read with the build's own "
                    "scene settings, the stored polytopes (one colour each; the values the C decodes), the build "
                    "summary, and DIR/trajectories.npz from `polycc sim` when present. Open the printed URL; "
                    "Ctrl-C stops it. World frame, metres.",
    )
    p.add_argument("dir", metavar="DIR", help="folder written by `polycc build` (and `polycc sim`)")
    p.add_argument("--scene", metavar="SCENE", help="the scene file (default: the one DIR was built from)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default: %(default)s; 0.0.0.0 for "
                                                         "other machines)")
    p.add_argument("--port", type=number(int, 1, 65535), default=8080, help="TCP port (default: %(default)s)")
    p.add_argument("--max-splats", type=number(int, 0, 10_000_000), default=MAX_SPLATS, metavar="N",
                   help="show at most N splats (a random subset beyond; 0 = cover only) (default: %(default)s)")
    p.add_argument("--duration", type=number(float, 0.0, lo_open=True, unit="s"), default=None, metavar="S",
                   help="stop after S seconds (default: run until Ctrl-C)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    d = Path(args.dir)
    if not (d / "manifest.json").is_file():
        raise PolyccError(f"{d}: no manifest.json; give a folder written by `polycc build`")
    settings, rec_scene = recorded_settings(d)
    scene_path = args.scene or rec_scene.get("path")
    ell, notes = None, []
    if args.max_splats and scene_path and Path(scene_path).is_file():
        check_scene_file(scene_path, rec_scene, str(d))
        with StageProgress() as progress:
            scene = pipeline.read(scene_path, settings, progress, warn) if settings else None
        ell = scene.ellipsoids if scene else None
    elif args.max_splats:
        notes.append(f"scene {scene_path} not found: cover only (pass --scene)")
        warn(f"the scene {scene_path} is not there; showing the cover only (pass --scene SCENE)")
    content = content_for(d, ell, notes)
    try:
        server = start(content, args.host, args.port, args.max_splats or 0)
    except OSError as exc:
        raise PolyccError(f"cannot serve on {args.host}:{args.port} ({exc.strerror or exc}); pick another --port") \
            from None
    url = f"http://{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:{server.get_port()}"
    console.print(f"view: {len(content.manifest['polytopes'])} polytopes, "
                  f"{0 if ell is None else min(len(ell), args.max_splats):,} splats, {len(content.flights)} flights "
                  f"-> open {url}  (Ctrl-C stops)", soft_wrap=True)
    try:
        t0 = time.monotonic()
        while args.duration is None or time.monotonic() - t0 < args.duration:
            time.sleep(0.2)
    finally:
        server.stop()
    return 0
