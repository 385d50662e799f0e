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
    _common_options(parser, default=None)
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
    # also after the command: `stage armature -q` as `stage -q armature`; an alias shares its command's parser
    for p in {id(p): p for p in sub.choices.values()}.values():
        _common_options(p, default=argparse.SUPPRESS)
    return parser


def _common_options(parser: argparse.ArgumentParser, *, default) -> None:
    """``-v``, ``-q`` and ``--progress``; on a subcommand their defaults are SUPPRESS, so that an
    option given before the command is kept when the command does not repeat it."""
    top = default is None
    parser.add_argument("-v", "--verbose", action="count", default=0 if top else default,
                        help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=False if top else default,
                        help="only warnings and errors (no progress bars)")
    parser.add_argument("--progress", action="store_true", default=False if top else default,
                        help="progress bars also when stderr is not a terminal (a file, a pipe)")


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
    bars = _progress_bars(args)
    from stage.drivers.base import CameraError

    try:
        if not bars:
            return int(args.func(args) or 0)
        from tqdm.contrib.logging import logging_redirect_tqdm

        with logging_redirect_tqdm():  # a log line is printed above the bars, never glued to one
            return int(args.func(args) or 0)
    except BrokenPipeError:  # `stage info | head`: the reader has gone; nothing more to say
        _silence_stdout()
        return 0
    except KeyboardInterrupt:
        print("stage: interrupted", file=sys.stderr)
        return 130
    except (UserError, ValueError, CameraError, FileNotFoundError, PermissionError, OSError) as exc:
        if args.verbose >= 2:
            raise
        print(f"stage {args.command}: error: {exc}", file=sys.stderr)
        return 2


def _progress_bars(args: argparse.Namespace) -> bool:
    """Whether the command shows progress bars: on a terminal (stderr), or with ``--progress``;
    never with ``-q`` or ``--no-progress``. Sets ``args.no_progress`` accordingly (for every
    command: those without the option read it too)."""
    shown = not getattr(args, "no_progress", False) and not args.quiet and (args.progress or sys.stderr.isatty())
    args.no_progress = not shown
    return shown


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so that the interpreter's final flush does not fail again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
