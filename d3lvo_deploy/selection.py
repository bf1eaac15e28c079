"""The pose choice's memory (`pt_select_hold`): the weighted pose held for a few pairs after the
graph's choice kept it. A vehicle that pulls the classical pose off the static scene stays in view
for several pairs, while the evidence that picked the weighted pose on one pair often falls just
under the thresholds on the next; the graph sees one pair, so the runtime keeps the count."""

from __future__ import annotations

import numpy as np

# the flow+pose graph's output where the model holds its choice: (1,) 1 where the pair's kept pose
# (`matrix`) is the weighted one (`start_next`), 0 where it is the classical one
SELECT_KEPT_OUTPUT = "select_kept"


def hold_step(kept: bool, left: int, hold: int) -> tuple[bool, int]:
    """(whether the pair's weighted pose is used, the pairs left to hold after this one): the
    weighted pose where the graph kept it, then on the `hold` pairs after (the count restarts at
    each pair it keeps); `left` the count after the previous pair, 0 at the start of a run."""
    if kept:
        return True, hold
    if left > 0:
        return True, left - 1
    return False, 0


def held_pose(out: dict, left: int, hold: int) -> tuple[np.ndarray, int]:
    """(the pair's kept motion (4,4) float64, the count after it) from a flow+pose graph's outputs
    (`matrix`, `start_next`, `SELECT_KEPT_OUTPUT`, batch row 0): `matrix`, or on a held pair the
    weighted pose `start_next` where it is finite. The runtime, `models.predict` and parity alike."""
    matrix = np.asarray(out["matrix"][0], np.float64)
    kept = bool(np.asarray(out[SELECT_KEPT_OUTPUT]).reshape(-1)[0] > 0.5)
    use, left = hold_step(kept, left, hold)
    weighted = np.asarray(out["start_next"][0], np.float64)
    return (weighted if use and not kept and np.all(np.isfinite(weighted)) else matrix), left
