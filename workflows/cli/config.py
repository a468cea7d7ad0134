"""``pbmdem config``: list the presets, print or validate a configuration."""

from __future__ import annotations

import argparse

HELP = "list presets, print or validate a configuration"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="preset name")
    parser.add_argument("--config", help="TOML configuration file to validate and print")
    parser.add_argument("--list", action="store_true", help="list the preset names")


def run(args: argparse.Namespace) -> int:
    from workflows.config import dump_toml, preset_names, resolve_config

    if args.list:
        print("\n".join(preset_names()))
        return 0
    print(dump_toml(resolve_config(args.preset, args.config)), end="")
    return 0
