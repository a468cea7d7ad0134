"""``pbmdem dem deck``: write a ready-to-run LIGGGHTS run directory.

``pbmdem dem deck --preset smoke --out DIR`` writes ``in.blender``, ``meshes/*.stl``,
``deck.json`` and the resolved ``config.toml`` (its first line records the deck hash) into
DIR; then ``cd DIR && liggghts -in in.blender``. ``--png`` also renders the geometry;
``--view-stl`` also writes STL files of the barrel and inlet wall (the deck uses primitives).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from workflows.cli_dem import add_config_arguments
from workflows.config import dump_toml, resolve_config

CONFIG_FILE = "config.toml"


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("deck", help="write a LIGGGHTS deck, meshes and the resolved config into a directory")
    add_config_arguments(parser)
    parser.add_argument("--out", required=True, help="run directory to create (or refresh)")
    parser.add_argument("--resume-from", default=None,
                        help="also write in.resume, continuing from this restart file (path relative to --out)")
    parser.add_argument("--png", action="store_true", help="also render the assembled geometry to geometry.png")
    parser.add_argument("--view-stl", action="store_true",
                        help="also write meshes/view_barrel.stl and meshes/view_inlet_wall.stl (viewing only; "
                             "the deck uses LIGGGHTS primitives for these)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dem.deck import MAIN_DECK, build_deck, deck_hash, write_deck

    config = resolve_config(preset=args.preset, config=args.config)
    files = build_deck(config.dem, resume_from=args.resume_from)  # validates before anything is written
    digest = deck_hash(files)
    files[CONFIG_FILE] = f"# deck_hash = {digest}\n" + dump_toml(config)
    out = write_deck(files, args.out)
    if args.view_stl:
        from dem.geometry import build_geometry, write_stl

        for name, mesh in build_geometry(config.dem).view_meshes.items():
            write_stl(mesh, Path(out) / "meshes" / f"view_{name}.stl")
    if args.png:
        from dem.render import render_geometry

        render_geometry(config.dem, Path(out) / "geometry.png")
    print(f"wrote {out / MAIN_DECK} (deck hash {digest}); run: cd {out} && liggghts -in {MAIN_DECK}")
    return 0
