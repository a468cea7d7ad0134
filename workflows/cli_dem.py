"""``pbmdem dem ...``: the DEM stage's subcommands (deck, run, post), one module each."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("dem", help="DEM stage: write decks, run LIGGGHTS, post-process dumps")
    dem_sub = parser.add_subparsers(dest="dem_command", required=True, metavar="DEM_COMMAND")
    from workflows import cli_dem_cluster, cli_dem_deck, cli_dem_run

    for module in (cli_dem_deck, cli_dem_run, cli_dem_cluster):
        module.register(dem_sub)


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """--preset NAME | --config FILE.toml, shared by every subcommand that needs a config."""
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--preset", help="preset name (see `pbmdem config --list`)")
    group.add_argument("--config", help="TOML configuration file")
