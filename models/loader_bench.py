"""Samples per second of the training loader, with and without `--depth-cache`:

    python -m models.loader_bench runs/data/tr_00 [--samples 60]

One process, no DataLoader: what one worker delivers. The point-head small preset; "with
augmentation" uses the default flips, rotations and brightness, "with the solver's inputs" what
`--solver-loss` loads (no flips or rotations)."""

from __future__ import annotations

import argparse
import tempfile
import time

from .config import D3LVOConfig
from .data import AugmentConfig, PairDataset


def samples_per_second(seq: str, solver: bool, cache: str | None, n: int) -> float:
    aug = AugmentConfig(flip=0.0, rotation_deg=0.0) if solver else AugmentConfig()
    data = PairDataset([seq], D3LVOConfig.small(pose_head="points"), augment=aug, solver=solver, cache=cache)
    n = min(n, len(data))
    t0 = time.perf_counter()
    for i in range(n):
        data[i]
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq")
    ap.add_argument("--samples", type=int, default=60)
    a = ap.parse_args()
    print("samples/s | no cache | first epoch (filling) | later epochs")
    for solver, name in ((False, "with augmentation"), (True, "with the solver's inputs")):
        with tempfile.TemporaryDirectory() as cache:
            rates = [samples_per_second(a.seq, solver, c, a.samples) for c in (None, cache, cache)]
        print(f"{name} | " + " | ".join(f"{r:.1f}" for r in rates), flush=True)


if __name__ == "__main__":
    main()
