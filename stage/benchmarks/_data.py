"""Where the real data live: ``../shared/data`` next to the project's checkout.

The benchmarks and the tests read the same datasets (the Sumner & Popovic horse, the Tzionas & Gall
pipe, caliscope's footage); this module is their one location. An installed package has no
checkout beside it, so there the data are absent and the benchmarks say so and skip them.
"""

from __future__ import annotations

from pathlib import Path

#: The project's checkout (the directory holding ``stage/``).
ROOT = Path(__file__).resolve().parents[2]
#: ``../shared/data`` next to the checkout; may not exist.
SHARED_DATA = ROOT.parent / "shared" / "data"
