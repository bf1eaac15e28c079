"""Training loop: AdamW on frame pairs, periodic validation through the project's evaluator,
atomic checkpoints. Runs as one process or under `torchrun --nproc_per_node N` (DDP; gloo on
CPU, nccl on GPU): rank 0 logs, validates and saves.
"""

from __future__ import annotations

import datetime
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch.utils.data import DataLoader, DistributedSampler, Sampler

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.metrics import auroc
from d3lvo_deploy.poses import Trajectory
from d3lvo_deploy.sequence import KittiSequence

from .checkpoint import load_checkpoint, save_checkpoint
from .config import SOLVER_KEYS, D3LVOConfig
from .d3lvo import D3LVO
from .data import AugmentConfig, PairDataset
from .loss import LossConfig, PoseLoss
from .predict import predict_sequence


@dataclass
class TrainConfig:
    data: list[str]
    out: str
    val: list[str] = field(default_factory=list)
    steps: int = 1000
    stop_at: int | None = None  # stop after this step (checkpoint saved); the schedule still spans `steps`
    batch_size: int = 4
    lr: float = 3e-4
    weight_decay: float = 1e-4
    balance_lr: float = 2e-2  # for the loss balance terms s_t, s_q
    grad_clip: float = 5.0
    warmup: int = 50  # linear warm-up steps, then cosine decay to 5 % of lr
    val_every: int = 500
    ckpt_every: int = 100
    seed: int = 0
    # start from these weights where names and shapes match (e.g. a model with another pose head)
    init: str | None = None
    num_workers: int = 0
    # a folder for each frame's projected depth input and solver points: later epochs read them
    # instead of reading and projecting the scans again (models.data.FrameLoader)
    depth_cache: str | None = None
    device: str = "auto"
    # fp32 | bf16 (autocast on CPU and GPU) | fp16 (GPU only, with a gradient scaler); the pose
    # solvers and the losses stay in fp32 either way
    precision: str = "fp32"
    dist_timeout_min: float = 180.0  # how long ranks wait for each other (rank 0's validation)
    # BatchNorm across DDP ranks: "sync" normalises by the global batch's statistics on GPUs
    # (SyncBatchNorm, as one process with the whole batch would; torch cannot sync them on the CPU,
    # where each rank keeps its own, as "local" does everywhere); "frozen" keeps every BN layer at
    # its running statistics (fine-tuning from a checkpoint), which makes R ranks of batch b train
    # exactly as one process of batch R*b
    batch_norm: str = "sync"
    # train only the parameters whose names start with one of these (e.g. "point_pose.moving", the
    # confidence net); the rest keep their weights and BatchNorm statistics, and no gradient flows
    # through them, so a step costs little more than the forward pass. Empty: train everything
    train_only: tuple[str, ...] = ()
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    loss: LossConfig = field(default_factory=LossConfig)


BATCH_NORMS = ("sync", "local", "frozen")

# the point solver's inputs in a sample (d3lvo_deploy.points.solver_feeds)
SOLVER_FEEDS = ("image1", "image2", "points1", "point_mask1", "image_intrinsics")


def fp32_outputs(out: dict) -> dict:
    """The network's outputs in float32 for the losses (bf16 would round the rotation error, ~1e-5,
    to nothing)."""
    def f(x):
        if isinstance(x, torch.Tensor):
            return x.float() if x.is_floating_point() else x
        if isinstance(x, (list, tuple)):
            return [f(v) for v in x]
        return x

    return {k: f(v) for k, v in out.items()}


def lr_factor(step: int, warmup: int, total: int) -> float:
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * progress))


def _dist_info() -> tuple[int, int, bool]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    return rank, world, world > 1


def _device(name: str, rank: int) -> torch.device:
    """torchrun's LOCAL_RANK picks the GPU of this node (RANK counts over all nodes)."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        local = int(os.environ.get("LOCAL_RANK", rank))
        dev = torch.device("cuda", local % max(torch.cuda.device_count(), 1))
        torch.cuda.set_device(dev)
        return dev
    return torch.device(name)


def validate(model: D3LVO, seqs: list[str]) -> dict:
    """t_rel/r_rel (when the path is long enough), ATE and RPE per validation sequence, and the
    pair errors of `pair_metrics` next to their baselines."""
    out = {}
    names = [Path(s).name for s in seqs]
    for s, name in zip(seqs, names):
        label = name if names.count(name) == 1 else str(s)  # A/sequences/09 and B/sequences/09 both kept
        est = predict_sequence(model, s)
        gt = KittiSequence.open(s).ground_truth
        res = evaluate(gt, Trajectory.from_poses(est), name=label)
        out[label] = {k: v for k, v in res.to_dict().items() if k in ("t_rel", "r_rel", "ate", "rpe_t", "rpe_r")}
        out[label].update(pair_metrics(model, [s]))
    return out


def val_score(val: dict) -> float:
    """Lower is better: mean t_rel over the validation sequences (ATE where a path is too short)."""
    return sum(m["t_rel"] if m["t_rel"] is not None else m["ate"] for m in val.values()) / max(len(val), 1)


def best_path(out: str | Path) -> Path:
    """Where training keeps the checkpoint with the best validation score: `<out stem>.best.pt`."""
    out = Path(out)
    return out.with_name(out.stem + ".best" + out.suffix)


def per_pair_mean(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The mean of `err` over each sample's `mask`, then over the batch, a sample without targets
    counting 0. Each pair weighs 1/B however many pixels it has, so the loss is linear in the
    batch: R DDP ranks with batch b average to exactly the loss of one process with batch R*b."""
    mask = mask.expand_as(err)
    total = torch.where(mask, err, torch.zeros_like(err)).flatten(1).sum(1)
    return (total / mask.flatten(1).sum(1).clamp(min=1)).mean()


def completion_loss(out: dict, batch: dict, device) -> torch.Tensor:
    """L1 (m) against dense depth where the sequence has it (synthetic depth_2/), within 80 m."""
    if "dense1" not in out:
        return torch.zeros((), device=device)
    pred = torch.cat([out["dense1"], out["dense2"]])
    gt = torch.cat([batch["gt_depth1"], batch["gt_depth2"]]).to(device)
    return per_pair_mean((pred - gt).abs(), (gt > 0) & (gt < 80))


def motion_loss(out: dict, batch: dict, device, shadows: bool = False) -> torch.Tensor:
    """BCE of the 'moves on its own' logits against the share of moving pixels in each cell's
    window, on samples that have motion masks (synthetic drives); with `shadows`, moving shadows
    count as moving where the sample has them (`LossConfig.moving_shadows`)."""
    if "moving_logits" not in out:
        return torch.zeros((), device=device)
    logits = out["moving_logits"]
    moving = batch["moving"].to(device)
    known = (moving.flatten(1).amin(1) >= 0).view(-1, 1, 1, 1)
    if shadows and "shadow" in batch:
        moving = torch.maximum(moving, batch["shadow"].to(device))  # -1 (unknown) leaves moving as it is
    target = cell_pool(moving.clamp(min=0), moving.shape[-1] // logits.shape[-1])
    bce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    return per_pair_mean(bce, known)


def cell_pool(x: torch.Tensor, s: int) -> torch.Tensor:
    """Mean over the (s+1)-wide window centred on each level cell's pixel s*i, the encoder's
    sampling (a plain s-wide pooling would centre it at s*i + (s-1)/2, half a cell off)."""
    return x if s == 1 else F.avg_pool2d(x, s + 1, stride=s, padding=s // 2)


def level_flow_target(flow: torch.Tensor, valid: torch.Tensor, shape) -> tuple[torch.Tensor, torch.Tensor]:
    """Full-resolution flow (px) -> a level's grid (cells): the mean over the pixels with a target
    in each cell's window (`cell_pool`). A cell counts when any of
    its pixels has a target, so sparse LiDAR targets (real KITTI: ~5 % of pixels) still
    supervise every cell they touch."""
    s = flow.shape[-1] // shape[-1]
    v = cell_pool(valid, s)
    return cell_pool(flow * valid, s) / v.clamp(min=1e-6) / s, v > 0


def flow_errors(flows: list[torch.Tensor], batch: dict, device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per flow level: (mean EPE of the prediction, mean EPE of predicting zero flow), in cells."""
    gt, valid = batch["flow"].to(device), batch["flow_valid"].to(device)
    out = []
    for f in flows:
        g, m = level_flow_target(gt, valid, f.shape[-2:])
        if m.any():
            out.append((((f - g).norm(dim=1, keepdim=True))[m].mean(), g.norm(dim=1, keepdim=True)[m].mean()))
    return out


def flow_loss(flows: list[torch.Tensor], batch: dict, device) -> torch.Tensor:
    """End-point error of each flow level against its target (true flow, else rigid), per pair
    (`per_pair_mean`), averaged over levels."""
    gt, valid = batch["flow"].to(device), batch["flow_valid"].to(device)
    errs = []
    for f in flows:
        g, m = level_flow_target(gt, valid, f.shape[-2:])
        errs.append(per_pair_mean((f - g).norm(dim=1, keepdim=True), m))
    return torch.stack(errs).mean() if errs else torch.zeros((), device=device)


def _rotation_deg(R: torch.Tensor) -> torch.Tensor:
    c = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(c))


@torch.no_grad()
def pair_metrics(model: D3LVO, seqs: list[str], pairs: int = 24) -> dict:
    """Frame-pair errors next to their baselines, on evenly spaced pairs of each sequence
    (no augmentation, the GN head started from the GT previous motion as in training):
    flow EPE per level against predicting zero flow, rotation error (deg) against predicting no
    rotation, translation error (m) against predicting no motion; on sequences with motion masks
    (`d3lvo synth --traffic`), per level the AUROC of low confidence for cells on moving vehicles
    and, where the drive has shadow_2/, for cells of moving shadows against cells that neither
    move nor are shaded by a mover (0.5 is what a uniform confidence scores)."""
    model.eval()
    data = PairDataset(seqs, model.cfg, augment=None)
    idx = np.linspace(0, len(data) - 1, min(pairs, len(data))).round().astype(int)
    dev = next(model.parameters()).device
    acc: dict[str, list[float]] = {}
    conf_scores: dict[int, list[np.ndarray]] = {}
    conf_labels: dict[int, list[np.ndarray]] = {}
    shadow_scores: dict[int, list[np.ndarray]] = {}
    shadow_labels: dict[int, list[np.ndarray]] = {}
    for i in idx:
        b = {k: v[None] for k, v in data[int(i)].items()}
        solver = {k: v.to(dev) for k, v in data.solver_inputs(int(i)).items()} if model.cfg.point_solver else None
        out = model(b["rgb1"].to(dev), b["rgb2"].to(dev), b["depth1"].to(dev), b["depth2"].to(dev),
                    b["K"].to(dev), b["init"].to(dev), solver)
        if float(b["moving"].min()) >= 0 and "confidence" in out:
            levels = (model.cfg.flow_levels[-1],) if model.cfg.point_solver else model.cfg.gn_levels
            for lvl, c in zip(levels, out["confidence"]):
                s = b["moving"].shape[-1] // c.shape[-1]
                moving = cell_pool(b["moving"], s) > 0.5  # as the flow targets
                score = -c.cpu().numpy().ravel()
                conf_scores.setdefault(lvl, []).append(score)
                conf_labels.setdefault(lvl, []).append(moving.numpy().ravel())
                if float(b["shadow"].min()) >= 0:  # moving shadows against what neither moves nor is shaded
                    shadow = (cell_pool(b["shadow"], s) > 0.5) & ~moving
                    keep = (shadow | (cell_pool(torch.maximum(b["moving"], b["shadow"]), s) == 0)).numpy().ravel()
                    shadow_scores.setdefault(lvl, []).append(score[keep])
                    shadow_labels.setdefault(lvl, []).append(shadow.numpy().ravel()[keep])
        for lvl, (e, z) in zip(model.cfg.flow_levels, flow_errors(out["flows"], b, dev)):
            acc.setdefault(f"flow_epe_l{lvl}", []).append(float(e))
            acc.setdefault(f"flow_epe_l{lvl}_zero", []).append(float(z))
        P, G = out["matrix"][0].cpu().double(), b["matrix"][0].double()
        acc.setdefault("rot_err_deg", []).append(float(_rotation_deg(P[:3, :3].T @ G[:3, :3])))
        acc.setdefault("rot_err_deg_zero", []).append(float(_rotation_deg(G[:3, :3])))
        acc.setdefault("trans_err_m", []).append(float((P[:3, 3] - G[:3, 3]).norm()))
        acc.setdefault("trans_err_m_zero", []).append(float(G[:3, 3].norm()))
    res = {k: float(np.mean(v)) for k, v in acc.items()}
    for lvl in conf_scores:
        a = auroc(np.concatenate(conf_scores[lvl]), np.concatenate(conf_labels[lvl]))
        if a is not None:
            res[f"moving_auroc_l{lvl}"] = a
    for lvl in shadow_scores:
        a = auroc(np.concatenate(shadow_scores[lvl]), np.concatenate(shadow_labels[lvl]))
        if a is not None:
            res[f"shadow_auroc_l{lvl}"] = a
    return res


def load_matching(model: D3LVO, path: str) -> int:
    """Copy a checkpoint's weights into `model` where name and shape agree; returns how many."""
    theirs = load_checkpoint(path)["model"]
    mine = model.state_dict()
    take = {k: v for k, v in theirs.items() if k in mine and mine[k].shape == v.shape}
    model.load_state_dict(take, strict=False)
    return len(take)


class EpochSampler(Sampler):
    """A fresh permutation per epoch from (seed, epoch), from `skip` samples on: a run resumed at
    step k draws exactly the batches an uninterrupted run would have drawn after step k."""

    def __init__(self, n: int, seed: int):
        self.n, self.seed, self.epoch, self.skip = n, seed, 0, 0

    def __iter__(self):
        # DistributedSampler's permutation: with R ranks, rank r takes every R-th index of it, so the
        # ranks' batches of a step together are this sampler's batch of R times their size
        g = torch.Generator().manual_seed(self.seed + self.epoch)
        return iter(torch.randperm(self.n, generator=g)[self.skip:].tolist())

    def __len__(self) -> int:
        return self.n - self.skip


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during training, after the current step was checkpointed."""

    def __init__(self, step: int, path: str):
        super().__init__(f"interrupted at step {step}")
        self.step, self.path = step, path


def _freeze_except(model: torch.nn.Module, prefixes: tuple[str, ...]) -> set[str]:
    """Stop gradients outside the named parts; returns the names of the modules left as they are."""
    if not prefixes:
        return set()
    if not any(n.startswith(prefixes) for n, _ in model.named_parameters()):
        raise D3LVOInputError(None, f"train_only {list(prefixes)} names no parameter of this model "
                                    "(names as in its state dict, e.g. point_pose.moving)")
    for n, p in model.named_parameters():
        p.requires_grad_(n.startswith(prefixes))
    return {n for n, m in model.named_modules() if n and not n.startswith(prefixes)
            and not any(p.requires_grad for p in m.parameters())}


def train(cfg: D3LVOConfig, tc: TrainConfig, resume: str | None = None,
          on_step: Callable[[int, dict], None] | None = None, on_note: Callable[[str], None] | None = None) -> dict:
    """Train; returns the final record (step, losses, validation). `on_step` drives a progress bar;
    `on_note` hears what the start took (`--init`'s tensors)."""
    rank, world, distributed = _dist_info()
    device = _device(tc.device, rank)
    if distributed and not dist.is_initialized():
        # rank 0 validates while the others wait at the next all-reduce: the full 09-10 validation
        # can take longer than NCCL's default timeout, so the group waits as long as one may take
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo",
                                timeout=datetime.timedelta(minutes=tc.dist_timeout_min))
    torch.manual_seed(tc.seed + rank)

    model = D3LVO(cfg).to(device)
    frozen = _freeze_except(model, tuple(tc.train_only))
    criterion = PoseLoss(tc.loss).to(device)
    params = list(model.parameters()) + list(criterion.parameters())
    # s_t, s_q must travel to log(typical error) (about -9 for frame-to-frame rotation): at the
    # network's lr Adam moves them ~lr per step, far too slowly for a short run, and weight decay
    # would pull them to 0; they get their own lr and no decay.
    opt = torch.optim.AdamW([
        {"params": list(model.parameters()), "lr": tc.lr, "weight_decay": tc.weight_decay},
        {"params": list(criterion.parameters()), "lr": tc.balance_lr, "weight_decay": 0.0},
    ])
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, tc.warmup, tc.steps))
    step, history = 0, []
    if resume:
        ck = load_checkpoint(resume, expect=cfg, ignore=SOLVER_KEYS)  # solver settings may change on resume
        model.load_state_dict(ck["model"])
        criterion.load_state_dict(ck["loss"])
        try:
            opt.load_state_dict(ck["optimizer"])
        except (ValueError, KeyError):
            raise D3LVOInputError(resume, "its optimizer state does not fit this trainer (older toolkit "
                                          "version?); train afresh instead of --resume") from None
        step, history = ck["step"], ck.get("history", [])
        if "rng" in ck:  # dropout draws continue where they stopped
            torch.set_rng_state(ck["rng"])
        sched.last_epoch = step
        for g, base in zip(opt.param_groups, sched.base_lrs):
            g["lr"] = base * lr_factor(step, tc.warmup, tc.steps)

    elif tc.init:
        taken = load_matching(model, tc.init)
        if taken == 0:
            raise D3LVOInputError(tc.init, "none of its weights fits this model config (name and shape); nothing to "
                                           "start from")
        if on_note is not None and rank == 0:  # what started from them: a partial match is a choice to see
            on_note(f"--init {tc.init}: {taken} of the model's {len(model.state_dict())} tensors taken (name and "
                    "shape match); the rest start fresh")
    if tc.batch_norm not in BATCH_NORMS:
        raise ValueError(f"batch_norm must be one of {', '.join(BATCH_NORMS)}, not {tc.batch_norm!r}")
    if distributed and tc.batch_norm == "sync" and device.type == "cuda":
        model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)  # same parameters and buffers
    ddp_model = torch.nn.parallel.DistributedDataParallel(model) if distributed else model
    amp_dtype = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}.get(tc.precision, "bad")
    if amp_dtype == "bad":
        raise ValueError(f"precision must be fp32, bf16 or fp16, not {tc.precision!r}")
    if tc.precision == "fp16" and device.type != "cuda":
        raise ValueError("fp16 training needs a CUDA GPU (its gradient scaler); use bf16 on the CPU")
    scaler = torch.amp.GradScaler(device.type, enabled=tc.precision == "fp16")
    if resume and ck.get("scaler"):  # fp16's loss scale continues where it stopped
        scaler.load_state_dict(ck["scaler"])
    solver_loss = tc.loss.solver_pose_weight > 0
    if solver_loss and not cfg.point_solver:
        raise ValueError("a pose loss through the solver needs the point head (pose_head='points')")
    augment = replace(tc.augment, flip=0.0, rotation_deg=0.0) if solver_loss else tc.augment
    data = PairDataset(tc.data, cfg, augment=augment, seed=tc.seed, solver=solver_loss, cache=tc.depth_cache)
    if len(data) == 0:
        raise D3LVOInputError(None, "no training pairs: the --data sequences need at least 2 frames")
    if distributed:
        sampler = DistributedSampler(data, num_replicas=world, rank=rank, seed=tc.seed, drop_last=True)
    else:
        sampler = EpochSampler(len(data), tc.seed)
    if not resume and tc.loss.balance_init == "data":
        criterion.init_balance(*data.identity_errors())
    batch = min(tc.batch_size, max(len(data) // world, 1))
    # its own generator: each new iterator draws a seed, which must not come from the global RNG
    # that dropout uses (a resumed run creates one iterator more than an uninterrupted one)
    loader = DataLoader(data, batch_size=batch, sampler=sampler, num_workers=tc.num_workers, drop_last=True,
                        pin_memory=device.type == "cuda",
                        generator=torch.Generator().manual_seed(tc.seed))

    record: dict = {}
    scored = [h for h in history if "val" in h]
    best = min((val_score(h["val"]) for h in scored), default=math.inf)
    per_epoch = max(len(data) // (batch * world), 1)
    epoch = step // per_epoch
    t0 = time.perf_counter()
    end = tc.steps if tc.stop_at is None else min(tc.steps, tc.stop_at)
    try:
        while step < end:
            data.epoch = epoch
            if distributed:
                sampler.set_epoch(epoch)
            else:
                sampler.epoch, sampler.skip = epoch, (step - epoch * per_epoch) * batch
            for b in loader:
                if step >= end:
                    break
                ddp_model.train()
                for name, m in model.named_modules():
                    if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and (
                            tc.batch_norm == "frozen" or name in frozen):
                        m.eval()
                solver = {k: b[k].to(device) for k in SOLVER_FEEDS} if solver_loss else None
                with torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None):
                    out = ddp_model(b["rgb1"].to(device), b["rgb2"].to(device), b["depth1"].to(device),
                                    b["depth2"].to(device), b["K"].to(device), b["init"].to(device), solver)
                out = fp32_outputs(out)
                if "poses" in out:
                    pose_loss, parts = criterion(out["poses"], out["pose"], b["pose"].to(device))
                    if solver_loss:
                        pose_loss = tc.loss.solver_pose_weight * pose_loss
                else:  # the point head: its pose is the solver's; its confidence learns from the masks
                    pose_loss, parts = torch.zeros((), device=device), {}
                comp = completion_loss(out, b, device)
                fl = flow_loss(out["flows"], b, device)
                mv = motion_loss(out, b, device, tc.loss.moving_shadows)
                loss = pose_loss + tc.loss.completion_weight * comp + tc.loss.flow_weight * fl + tc.loss.motion_weight * mv
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"loss became {float(loss)} at step {step}")
                opt.zero_grad(set_to_none=True)
                scaler.scale(loss).backward()
                scaler.unscale_(opt)  # clipping sees the true gradients
                if distributed:
                    # DDP averages the model's gradients only; s_t, s_q sit outside it. Averaged here
                    # too, every rank sees the same gradients, so clipping scales them alike and the
                    # replicas stay identical
                    for q in criterion.parameters():
                        if q.grad is not None:
                            dist.all_reduce(q.grad)
                            q.grad /= world
                torch.nn.utils.clip_grad_norm_(params, tc.grad_clip)
                scaler.step(opt)  # skips the step where fp16 gradients overflowed
                scaler.update()
                sched.step()
                step += 1
                record = {"step": step, "loss": float(loss.detach()), "pose_loss": float(pose_loss.detach()),
                          "completion_l1": float(comp.detach()), "flow_epe": float(fl.detach()),
                          "motion_bce": float(mv.detach()),
                          "s_t": float(criterion.s_t.detach()),
                          "s_q": float(criterion.s_q.detach()), **parts,
                          "seconds": time.perf_counter() - t0}
                if rank == 0:
                    if tc.val and (step % tc.val_every == 0 or step == tc.steps):
                        record["val"] = validate(model, tc.val)
                        if val_score(record["val"]) < best:
                            # long CPU runs overfit small synthetic sets: keep the best validated weights
                            best = val_score(record["val"])
                            record["best"] = True
                            save_checkpoint(best_path(tc.out), model, cfg, loss=criterion.state_dict(), step=step,
                                            history=history + [record], train_config=asdict(tc))
                    history.append(record)
                    if step % tc.ckpt_every == 0 or step == end:
                        save_checkpoint(tc.out, model, cfg, loss=criterion.state_dict(), optimizer=opt.state_dict(),
                                        step=step, history=history, train_config=asdict(tc), rng=torch.get_rng_state(),
                                        scaler=scaler.state_dict())
                    if on_step is not None:
                        on_step(step, record)
            epoch += 1
    except KeyboardInterrupt:
        # Ctrl-C: keep the step just finished, so that --resume loses nothing
        if rank == 0 and step > 0:
            save_checkpoint(tc.out, model, cfg, loss=criterion.state_dict(), optimizer=opt.state_dict(),
                            step=step, history=history, train_config=asdict(tc), rng=torch.get_rng_state(),
                                        scaler=scaler.state_dict())
        raise TrainingInterrupted(step, tc.out) from None
    if distributed:
        dist.barrier()
        dist.destroy_process_group()
    return record

