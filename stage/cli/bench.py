"""``stage bench NAME``: benchmarks that print measured figures.

Every module in :mod:`stage.benchmarks` that defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args)`` is one benchmark.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil

ORDER = 90


def register(sub: argparse._SubParsersAction) -> None:
    import stage.benchmarks as benchmarks

    p = sub.add_parser(
        "bench",
        help="run a benchmark and print its figures",
        description="Benchmarks print measured speed and memory figures (no pass/fail).",
    )
    bsub = p.add_subparsers(dest="bench", metavar="NAME", required=True)
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda i: i.name):
        mod = importlib.import_module(f"stage.benchmarks.{info.name}")
        if not hasattr(mod, "run"):
            continue
        bp = bsub.add_parser(mod.NAME, aliases=getattr(mod, "ALIASES", ()), help=mod.HELP, description=mod.HELP)
        mod.add_arguments(bp)
        bp.set_defaults(func=mod.run)
