"""``pbmdem study NAME``: the research studies, each a module of :mod:`workflows.studies`
with ``HELP``, ``add_arguments`` and ``run``. They import the product; the product never
imports them."""

from __future__ import annotations

import argparse
import importlib

HELP = "research studies on DEM runs (why the transport model is what it is)"

#: (subcommand, module)
STUDIES = (
    ("lag", "workflows.studies.lag"),
    ("layers", "workflows.studies.layers"),
    ("phases", "workflows.studies.phases"),
    ("composition", "workflows.studies.composition"),
    ("sizes", "workflows.studies.sizes"),
    ("holdout", "workflows.studies.holdout"),
    ("startup", "workflows.studies.startup"),
    ("feeders", "workflows.studies.feeders"),
    ("blocks", "workflows.studies.blocks"),
    ("vrr", "workflows.studies.vrr"),
    ("budget", "workflows.studies.budget"),
    ("fill", "workflows.studies.fill"),
    ("paper-scale", "workflows.studies.paper_scale"),
    ("law", "workflows.studies.law"),
    ("suggest", "workflows.studies.suggest"),
    ("profile-forms", "workflows.studies.profile_forms"),
    ("error-structure", "workflows.studies.error_structure"),
    ("series", "workflows.studies.series"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="study", required=True, metavar="STUDY")
    for name, module_name in STUDIES:
        module = importlib.import_module(module_name)
        study = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(study)
        study.set_defaults(func=module.run)
