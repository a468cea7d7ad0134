"""``pbmdem config``: list the presets, print or validate a configuration, describe its keys."""

from __future__ import annotations

import argparse

HELP = "list presets, print or validate a configuration, describe its keys"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="preset name")
    parser.add_argument("--config", help="TOML configuration file to validate and print")
    parser.add_argument("--list", action="store_true", help="list the preset names")
    parser.add_argument(
        "--describe",
        nargs="?",
        const="",
        metavar="KEY",
        help="every key's type, unit, default, valid range and meaning; KEY (e.g. dem.geometry.length_m "
        "or dem.contact) one key or one section",
    )
    parser.add_argument(
        "--markdown",
        action="store_true",
        help="--describe as a Markdown page (the whole page is workflows/CONFIG.md)",
    )


def run(args: argparse.Namespace) -> int:
    from workflows.config import dump_toml, preset_names, resolve_config

    if args.list:
        print("\n".join(preset_names()))
        return 0
    if args.describe is not None or args.markdown:
        from workflows.config_reference import describe, reference_markdown, reference_text

        sections = describe(args.describe)
        print(reference_markdown(sections) if args.markdown else reference_text(sections), end="")
        return 0
    print(dump_toml(resolve_config(args.preset, args.config)), end="")
    return 0
