"""Run by tests/test_training.py under torchrun (or alone, as one process): `d3lvo train` for a few
steps, as a user starts it, then a hash of this rank's replica (network weights and the loss
balance terms) to OUT/rank_N.txt and the weights themselves to OUT/rank_N.pt.

    ddp_replica.py DATA OUT GRAD_CLIP BATCH_SIZE BATCH_NORM"""

import hashlib
import os
import sys

import torch

import models.train as T
from cli.main import app

made: dict[str, object] = {}


class _Model(T.D3LVO):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        made["model"] = self


class _Loss(T.PoseLoss):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        made["loss"] = self


T.D3LVO, T.PoseLoss = _Model, _Loss
data, out, clip, batch, bn = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
torch.set_num_threads(1)
os.makedirs(out, exist_ok=True)
config = f"{out}/train.toml"
with open(config, "w") as fh:  # dropout off: its draws differ between ranks
    fh.write(f'[model]\npreset = "small"\nheight = 64\nwidth = 224\ndropout = 0.0\n\n'
             f'[train]\ngrad_clip = {clip}\nbatch_norm = "{bn}"\nwarmup = 1\n')
try:
    app(["train", "--config", config, "--data", data, "--out", f"{out}/ck.pt", "--steps", "3", "--batch-size",
         str(batch), "--lr", "1e-3", "--device", "cpu", "--ckpt-every", "100"])
except SystemExit as e:
    if e.code:
        raise
h = hashlib.sha256()
for m in (made["model"], made["loss"]):
    for p in m.parameters():
        h.update(p.detach().numpy().tobytes())
rank = int(os.environ.get("RANK", "0"))  # train() has closed the process group by now
torch.save({"model": made["model"].state_dict(), "loss": made["loss"].state_dict()}, f"{out}/rank_{rank}.pt")
with open(f"{out}/rank_{rank}.txt", "w") as fh:
    fh.write(f"{h.hexdigest()} {float(made['loss'].s_t):.9g} {float(made['loss'].s_q):.9g}\n")
