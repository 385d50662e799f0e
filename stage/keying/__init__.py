"""Chroma keying: silhouettes a visual hull can trust.

One algorithm per module: :mod:`~stage.keying.chroma` (shading-invariant chroma
distance), :mod:`~stage.keying.luma` (dark/bright backdrops),
:mod:`~stage.keying.plate` (background-plate difference),
:mod:`~stage.keying.cleanup` (soft matte, coverage rule, hysteresis, specks and
holes), :mod:`~stage.keying.spill` (despill), :mod:`~stage.keying.metrics` (IoU,
boundary F-score), :mod:`~stage.keying.preview` (contact sheets), and
:mod:`~stage.keying.keyer` which runs them on a camera's frames.
"""

from stage.keying.keyer import estimate_model, key_frames, key_one
from stage.keying.metrics import boundary_f_score, iou, mask_boundary
from stage.keying.params import KEY_MODES, KeyingError, KeyParams, KeyResult
from stage.keying.preview import contact_sheet
from stage.keying.spill import despill
from stage.keying.take import key_take

__all__ = [
    "KEY_MODES",
    "KeyParams",
    "KeyResult",
    "KeyingError",
    "key_frames",
    "key_one",
    "key_take",
    "estimate_model",
    "despill",
    "contact_sheet",
    "iou",
    "boundary_f_score",
    "mask_boundary",
]
