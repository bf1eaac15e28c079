"""`python -m models.pair_eval CKPT SEQ [SEQ ...]`: a checkpoint's frame-pair errors beside their
baselines on held-out sequences (flow EPE against zero flow per level, rotation against no
rotation, translation against no motion), the numbers "the flow is learned" and "it predicts
rotation" rest on. Same function as the training's validation (`models.train.pair_metrics`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

from d3lvo_deploy.errors import D3LVOInputError

from .checkpoint import build_model, load_checkpoint
from .train import pair_metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("ckpt")
    ap.add_argument("seqs", nargs="+")
    ap.add_argument("--pairs", type=int, default=48, help="evenly spaced pairs per sequence")
    args = ap.parse_args()
    if args.pairs < 1:
        ap.error(f"--pairs must be at least 1, not {args.pairs}")
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    try:
        model = build_model(load_checkpoint(args.ckpt))
        for s in args.seqs:
            m = pair_metrics(model, [s], pairs=args.pairs)
            print(json.dumps({"sequence": s, **{k: round(v, 4) for k, v in m.items()}}))
    except D3LVOInputError as e:  # a missing checkpoint or drive: one line, as the d3lvo commands
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
