"""Run by tests/test_training.py under torchrun (or alone, as one process): trains a few steps and
writes a hash of this rank's replica (network weights and the loss balance terms) to
OUT/rank_N.txt and the weights themselves to OUT/rank_N.pt.

    ddp_replica.py DATA OUT GRAD_CLIP BATCH_SIZE BATCH_NORM"""

import hashlib
import os
import sys

import torch

import models.train as T
from models.config import D3LVOConfig

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
cfg = D3LVOConfig.small(height=64, width=224, dropout=0.0)  # dropout draws differ between ranks
T.train(cfg, T.TrainConfig(data=[data], out=f"{out}/ck.pt", steps=3, batch_size=batch, grad_clip=clip, device="cpu",
                           ckpt_every=100, batch_norm=bn, lr=1e-3, warmup=1))
h = hashlib.sha256()
for m in (made["model"], made["loss"]):
    for p in m.parameters():
        h.update(p.detach().numpy().tobytes())
rank = int(os.environ.get("RANK", "0"))  # train() has closed the process group by now
torch.save({"model": made["model"].state_dict(), "loss": made["loss"].state_dict()}, f"{out}/rank_{rank}.pt")
with open(f"{out}/rank_{rank}.txt", "w") as fh:
    fh.write(f"{h.hexdigest()} {float(made['loss'].s_t):.9g} {float(made['loss'].s_q):.9g}\n")
