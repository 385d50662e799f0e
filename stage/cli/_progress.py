"""One tqdm bar per pipeline step, fed by ``progress(step, done, total)`` callbacks."""

from __future__ import annotations

from tqdm import tqdm


class StepBars:
    """Callable ``(step, done, total)`` that keeps one progress bar per step; use as a context manager."""

    def __init__(self, *, disable: bool = False) -> None:
        self.disable = disable
        self._bars: dict[str, tqdm] = {}

    def __call__(self, step: str, done: int, total: int) -> None:
        bar = self._bars.get(step)
        if bar is None:
            bar = self._bars[step] = tqdm(total=total, desc=step, unit="frame", disable=self.disable)
        elif done == 0 and bar.n == 0:  # announced before it ran: its clock (rate, time left) starts now
            bar.reset(total=total)
            return
        bar.n = done
        bar.refresh()

    def __enter__(self) -> "StepBars":
        return self

    def __exit__(self, *exc) -> None:
        for b in self._bars.values():
            b.close()
