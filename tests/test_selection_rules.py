"""The pose choice's rules with a memory in scripts/selection_rules.py, on hand-built pair records."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rules():
    pytest.importorskip("torch")
    spec = importlib.util.spec_from_file_location("selection_rules", ROOT / "scripts" / "selection_rules.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


def pair(gain=0.0, share=0.2, scan_w=1.0, scan_c=1.0, rotation=0.1):
    return {"gain": gain, "rotation": rotation, "share": share, "scan_W": scan_w, "scan_C": scan_c}


def test_hold_and_latch_by_hand(rules):
    """The bundled model's selection (`pt_select` 0.003 with the rotation test at 0.05 degrees,
    the cap at 70 % distrusted, or frame t's scan error of the weighted pose below 0.7 times the
    classical one's) keeps the weighted pose on pair 1 (its gain) and pair 6 (the scan's pass; the
    cap stops the gain there). Held for two pairs after each, it is kept on 1-3 and 6-7; held while
    the scan fits it no worse than the classical pose (or cannot judge: no trusted point on a
    return), on 1-4 (pair 4's 0.95, pair 5's 1.2 ends it) and 6-7 (pair 7 has no evidence)."""
    ships = rules.with_cap_or_scan(rules.photometric_test(*rules.AS_SHIPPED))
    drive = [pair(), pair(gain=0.01), pair(scan_w=0.9), pair(scan_w=1.0), pair(scan_w=0.95), pair(scan_w=1.2),
             pair(gain=0.01, share=0.9, scan_w=0.5), pair(scan_w=rules.NO_EVIDENCE)]
    assert [ships(drive, i) for i in range(len(drive))] == [False, True, False, False, False, False, True, False]
    hold = rules.held_after(ships, 2)
    assert [hold(drive, i) for i in range(len(drive))] == [False, True, True, True, False, False, True, True]
    latch = rules.latched(ships, lambda ps, i: rules.scan_fits(ps, i, "scan", 1.0, False) is not False)
    assert [latch(drive, i) for i in range(len(drive))] == [False, True, True, True, True, False, True, True]
    # each drive's choices are its own: a drive that starts where this one's pair 4 is, unlatched
    other = [pair(scan_w=0.95), pair(scan_w=0.95)]
    assert [latch(other, i) for i in range(len(other))] == [False, False]
    assert latch(drive, 4) and not latch(drive, 5)


def test_held_after_is_what_the_runtime_holds(rules):
    """The replay's rule (the weighted pose where any of the last h + 1 pairs kept it) against the
    runtime's count (`d3lvo_deploy.selection.hold_step`, `pt_select_hold`) on random choices."""
    import numpy as np

    from d3lvo_deploy.selection import hold_step

    rng = np.random.default_rng(0)
    for hold in (1, 2, 4):
        choice = [bool(c) for c in rng.random(60) < 0.15]
        rule = rules.held_after(lambda ps, i: ps[i], hold)
        left, used = 0, []
        for kept in choice:
            use, left = hold_step(kept, left, hold)
            used.append(use)
        assert used == [rule(choice, i) for i in range(len(choice))]
        assert used != choice  # the hold engaged
