"""A pipeline's named steps, in order."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

__all__ = ["Step", "StepList"]


@dataclass(frozen=True)
class Step:
    """One named step: ``run(run)`` does the work on a :class:`pipeline.run.Run` and persists it;
    ``totals(run)``, the progress entries ``(name, total)`` it reports, announced before the run's
    first step (:meth:`pipeline.run.Run.announce`)."""

    name: str
    run: Callable
    doc: str = ""
    totals: Callable | None = None


class StepList(Sequence[str]):
    """The names of a pipeline's steps in the order they run (a sequence of ``str``), and the steps.

    One object for the pipeline's life: :meth:`register` changes it in place, so a name imported
    from the module that holds it (``from pipeline.process import STEPS``) always sees every step.
    """

    def __init__(self) -> None:
        self._steps: dict[str, Step] = {}

    def register(self, name: str, run: Callable, *, doc: str = "", after: str | None = None,
                 totals: Callable | None = None) -> None:
        """Add (or move) a step, after ``after`` (default at the end)."""
        if not name or not name.isidentifier():
            raise ValueError(f"name must be an identifier, got {name!r}")
        if after is not None and after not in self._steps:
            raise ValueError(f"after: no step {after!r} (steps: {list(self._steps)})")
        items = [(n, s) for n, s in self._steps.items() if n != name]
        pos = len(items) if after is None else [n for n, _ in items].index(after) + 1
        items.insert(pos, (name, Step(name=name, run=run, doc=doc, totals=totals)))
        self._steps = dict(items)

    def remove(self, name: str) -> None:
        """Take a step out (``KeyError`` when there is none of that name)."""
        del self._steps[name]

    def step(self, name: str) -> Step:
        return self._steps[name]

    def __getitem__(self, i):
        names = tuple(self._steps)
        return names[i]

    def __len__(self) -> int:
        return len(self._steps)

    def __iter__(self) -> Iterator[str]:
        return iter(tuple(self._steps))

    def __contains__(self, name: object) -> bool:
        return name in self._steps

    def __repr__(self) -> str:
        return f"StepList{tuple(self._steps)!r}"
