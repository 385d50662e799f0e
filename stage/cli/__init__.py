"""The ``stage`` command line.

Every module in this package that defines ``register(subparsers)`` adds one
subcommand; ``register`` creates its parser and sets ``func`` (called with the
parsed arguments, returning an exit code). Subcommands are found automatically,
so adding a command is adding a module.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from stage import __version__

__all__ = ["main", "build_parser"]

log = logging.getLogger("stage")


class UserError(Exception):
    """An error the user can fix; printed without a traceback."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stage",
        description="capture-stage: drive a multi-camera capture stage, calibrate it, "
        "and turn its takes into spines (branching, temporally consistent skeletons).",
    )
    parser.add_argument("--version", action="version", version=f"capture-stage {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "register"):
            modules.append(mod)
    modules.sort(key=lambda m: (getattr(m, "ORDER", 50), m.__name__))
    for mod in modules:
        mod.register(sub)
    return parser


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.INFO if verbose <= 1 else logging.DEBUG)
    if verbose == 0 and not quiet:
        level = logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    # libraries that set their own loggers' levels (Dask's distributed logs at INFO) pass the root's
    # level; the handler's level holds -q for them too
    handler.setLevel(level)
    logging.basicConfig(level=level, handlers=[handler])  # no change when logging is set up already


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    _setup_logging(args.verbose, args.quiet)
    if args.quiet and hasattr(args, "no_progress"):
        args.no_progress = True  # -q silences progress bars as well as log messages
    from stage.drivers.base import CameraError

    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("stage: interrupted", file=sys.stderr)
        return 130
    except (UserError, ValueError, CameraError, FileNotFoundError, PermissionError, OSError) as exc:
        if args.verbose >= 2:
            raise
        print(f"stage {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
