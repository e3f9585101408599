"""The ``cpdetect`` command line.

Each sub-command lives in its own module under ``cpdetect.commands`` with a ``register(subparsers)``
function that adds its parser and sets ``func`` (``func(args) -> int`` exit code). Errors the user can
fix are :class:`~cpdetect.errors.CpdetectError` and print as one line; anything else prints one line
too (with ``--debug`` for the traceback), and the exit code is non-zero.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

from .errors import CpdetectError

DESCRIPTION = ("Find control-point markers (2x2 checker targets) in photographs and georeference "
               "3D models with them.")

COMMAND_MODULES = (
    "synth", "evaluate", "detect", "train", "export", "register", "georef", "compare", "demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cpdetect", description=DESCRIPTION)
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"cpdetect.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"cpdetect.commands.{name}":
                continue  # command not built in this version
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO,
                        format="%(levelname)s: %(message)s", stream=sys.stderr)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except CpdetectError as exc:
        print(f"cpdetect {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"cpdetect {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    except MemoryError:
        print(f"cpdetect {args.command}: error: out of memory", file=sys.stderr)
        return 1
    except Exception as exc:  # never a traceback for users; --debug shows it
        if args.debug:
            raise
        print(f"cpdetect {args.command}: internal error: {type(exc).__name__}: {exc} "
              "(rerun with --debug for details)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
