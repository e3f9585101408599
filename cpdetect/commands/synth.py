"""``cpdetect synth KIND``: generate synthetic data with known truth (``images``, ``scene``)."""
from __future__ import annotations

import importlib

KIND_MODULES = ("synth_images", "synth_scene")


def register(sub) -> None:
    parser = sub.add_parser("synth", help="generate synthetic data with known truth")
    kinds = parser.add_subparsers(dest="synth_kind", metavar="KIND")
    for name in KIND_MODULES:
        try:
            module = importlib.import_module(f"cpdetect.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"cpdetect.commands.{name}":
                continue
            raise
        module.register(kinds)

    def _help(args) -> int:
        parser.print_help()
        return 2

    parser.set_defaults(func=_help)
