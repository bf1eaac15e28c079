"""Evaluate estimated trajectories against ground truth, one sequence or many.

Both trajectories are first expressed relative to their first common frame (so a run starting at
identity and a GT file starting elsewhere compare), then the estimate is aligned as asked:
`none`, `6dof` (SE(3) Umeyama), `7dof` (Sim(3) Umeyama) or `scale` (scale only, for monocular
methods). The aligned estimate feeds every metric, as in kitti-odom-eval.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import metrics
from .errors import D3LVOInputError
from .geometry import apply_sim3, relative, umeyama
from .poses import Trajectory, read_poses

ALIGN_MODES = ("none", "6dof", "7dof", "scale")


@dataclass
class SequenceResult:
    name: str
    frames: int
    path_length_m: float
    t_rel: float | None  # %
    r_rel: float | None  # deg / 100 m
    ate: float  # m, RMSE after alignment
    rpe_t: float  # m, mean frame-to-frame
    rpe_r: float  # deg, mean frame-to-frame
    segments: int
    scale: float = 1.0
    notes: list[str] = field(default_factory=list)
    segment_rows: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)), repr=False)
    gt_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False)
    est_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)), repr=False)  # aligned

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("segment_rows", "gt_poses", "est_poses"):
            d.pop(k)
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in d.items()}  # JSON: null


@dataclass
class EvalReport:
    sequences: list[SequenceResult]
    align: str
    # folders of NN.txt files: the per-sequence shape even where one sequence pairs up, so that a
    # script reading it does not depend on how many did
    per_sequence: bool = False

    @property
    def overall(self) -> dict:
        """The devkit's aggregate: segments of all sequences pooled, so longer sequences weigh more;
        ATE the RMSE over every frame of them all (each sequence's RMSE, pooled), RPE the mean."""
        rows = np.concatenate([s.segment_rows for s in self.sequences]) if self.sequences else np.zeros((0, 5))
        t_rel, r_rel = metrics.rel_errors(rows)
        frames = np.array([s.frames for s in self.sequences], dtype=np.float64)
        return {
            "t_rel": None if math.isnan(t_rel) else t_rel,
            "r_rel": None if math.isnan(r_rel) else r_rel,
            "ate": float(np.sqrt(np.average(np.square([s.ate for s in self.sequences]), weights=frames))),
            "rpe_t": _finite_average([s.rpe_t for s in self.sequences], frames),
            "rpe_r": _finite_average([s.rpe_r for s in self.sequences], frames),
            "segments": int(len(rows)),
            "frames": int(frames.sum()),
        }

    def to_dict(self) -> dict:
        """One sequence: its numbers at top level; several, or folders: `sequences` plus the pooled
        mean on top."""
        if len(self.sequences) == 1 and not self.per_sequence:
            return {**self.sequences[0].to_dict(), "align": self.align}
        return {**self.overall, "align": self.align, "sequences": [s.to_dict() for s in self.sequences]}


def _finite_average(values: list[float], weights: np.ndarray) -> float | None:
    """The weighted mean of the sequences that have the value (RPE needs adjacent frames)."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v)
    return float(np.average(v[ok], weights=weights[ok])) if ok.any() else None


def align_estimate(gt: np.ndarray, est: np.ndarray, mode: str) -> tuple[np.ndarray, float]:
    """Return the aligned estimate and the scale that was applied."""
    if mode == "none":
        return est, 1.0
    if mode == "scale":
        g, e = gt[:, :3, 3], est[:, :3, 3]
        den = float((e * e).sum())
        s = float((g * e).sum()) / den if den > 0 else 1.0
        out = est.copy()
        out[:, :3, 3] *= s
        return out, s
    if mode in ("6dof", "7dof"):
        R, t, s = umeyama(est[:, :3, 3], gt[:, :3, 3], with_scale=mode == "7dof")
        return apply_sim3(est, R, t, s), s
    raise ValueError(f"align must be one of {ALIGN_MODES}, not {mode!r}")


SCALE_HINT = 1.5  # path-length ratio beyond which a result looks up to scale rather than wrong


def path_length(poses: np.ndarray) -> float:
    """Metres travelled along (N,4,4) poses."""
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def pair_by_time(gt: Trajectory, est: Trajectory) -> tuple[Trajectory, np.ndarray | None, str | None]:
    """Where both files carry stamps on one clock (TUM), each estimate pose's nearest ground-truth
    pose, within half the ground truth's median interval: (the estimate's poses that have one,
    their GT positions, a note counting those left out, as evo's association leaves them out).
    Times on another clock altogether (not overlapping) pair by order, with a note; untimed files,
    by order or frame number (`_by_order`): positions None."""
    if est.timestamps is None or gt.timestamps is None or len(gt) < 2:
        return est, None, None
    if est.timestamps[-1] < gt.timestamps[0] or est.timestamps[0] > gt.timestamps[-1]:
        return est, None, "the estimate's times do not overlap the ground truth's (another clock?): paired by order"
    pos = np.clip(np.searchsorted(gt.timestamps, est.timestamps), 1, len(gt) - 1)
    pos = np.where(np.abs(gt.timestamps[pos - 1] - est.timestamps) <= np.abs(gt.timestamps[pos] - est.timestamps),
                   pos - 1, pos)
    tol = 0.5 * float(np.median(np.diff(gt.timestamps)))
    near = np.abs(gt.timestamps[pos] - est.timestamps) <= tol
    if near.all():
        return est, pos, None
    keep = np.flatnonzero(near)
    note = f"{len(near) - len(keep)} of {len(near)} poses have no ground-truth pose within {tol:.3g} s: left out"
    return Trajectory(est.poses[keep], np.arange(len(keep)), est.timestamps[keep]), pos[keep], note


def _by_order(gt: Trajectory, est: Trajectory, est_name: str | Path) -> np.ndarray:
    """GT positions by frame number where both files number their frames (13 columns), else by
    order (an estimate's own frame numbers count as positions in a ground truth that does not
    number its frames)."""
    ids = est.frame_ids
    if ids.min(initial=0) < 0:
        raise D3LVOInputError(est_name, f"frame index {int(ids.min())} is negative")
    if est.numbered and gt.numbered:  # both number their frames: by number
        pos = np.clip(np.searchsorted(gt.frame_ids, ids), 0, len(gt) - 1)
        missing = gt.frame_ids[pos] != ids
        if missing.any():
            raise D3LVOInputError(est_name, f"frame {int(ids[np.argmax(missing)])} is not among the ground truth's "
                                            "numbered frames")
        return pos
    if ids.max(initial=-1) >= len(gt):
        raise D3LVOInputError(est_name, f"frame index {int(ids.max())} is outside the {len(gt)} GT frames")
    return ids


def match_frames(gt: Trajectory, est: Trajectory, est_name: str | Path = "estimate",
                 timed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Pair estimate poses with GT frames (at `timed`, the positions `pair_by_time` found, else
    `_by_order`); returns (GT position of each estimate pose, valid mask over GT, notes)."""
    notes: list[str] = []
    if len(est) > len(gt):
        raise D3LVOInputError(est_name, f"{len(est)} poses but the ground truth has only {len(gt)}")
    if timed is not None and np.any(np.diff(timed) <= 0):
        k = int(np.argmax(np.diff(timed) <= 0))
        raise D3LVOInputError(est_name, f"poses {k} and {k + 1} (t = {est.timestamps[k]:.6f}, "
                                        f"{est.timestamps[k + 1]:.6f} s) fall on the same ground-truth pose: "
                                        "the estimate is faster than the ground truth")
    ids = timed if timed is not None else _by_order(gt, est, est_name)
    if len(est) < len(gt) and np.array_equal(ids, np.arange(len(est))):
        notes.append(f"estimate has {len(est)} of {len(gt)} poses: evaluated on the first {len(est)} frames")
    elif len(est) < len(gt):
        notes.append(f"estimate skips {len(gt) - len(est)} frames: segments touching them are left out")
    valid = np.zeros(len(gt), dtype=bool)
    valid[ids] = True
    return ids, valid, notes


def evaluate(gt: Trajectory | np.ndarray, est: Trajectory | np.ndarray, align: str = "none", name: str = "",
             est_name: str | Path = "estimate", gt_name: str | Path | None = None) -> SequenceResult:
    """The devkit's t_rel / r_rel, ATE and RPE of `est` against `gt` (Trajectory, or (N,4,4) /
    (N,3,4) pose arrays, one per frame); `align` (ALIGN_MODES) before scoring."""
    gt = gt if isinstance(gt, Trajectory) else Trajectory.from_poses(gt)
    est = est if isinstance(est, Trajectory) else Trajectory.from_poses(est)
    est, timed, how = pair_by_time(gt, est)
    if len(est) < 2 or len(gt) < 2:
        raise D3LVOInputError(est_name if len(est) < 2 else gt_name, "need at least 2 poses to evaluate"
                              + (f" ({how})" if how and timed is not None else ""))
    ids, valid, notes = match_frames(gt, est, est_name, timed)
    notes = ([how] if how else []) + notes
    last = int(ids[-1])
    gt_poses = gt.poses[: last + 1]
    valid = valid[: last + 1]
    first = int(ids[0])
    gt_rel = relative(gt_poses[first], gt_poses)
    est_rel = relative(est.poses[0], est.poses)
    aligned, scale = align_estimate(gt_rel[ids], est_rel, align)
    if align in ("none", "6dof"):
        ratio = path_length(est_rel) / max(path_length(gt_rel[ids]), 1e-9)
        if not 1 / SCALE_HINT < ratio < SCALE_HINT:
            notes.append(f"the estimate's path is {ratio:.3g}x the ground truth's: up to scale (monocular)? "
                         "score it with --align 7dof")

    full = np.tile(np.eye(4), (len(gt_rel), 1, 1))
    full[ids] = aligned
    rows = metrics.segment_errors(gt_rel, full, valid)
    path_len = float(metrics.trajectory_distances(gt_rel[first:])[-1])  # the stretch the estimate covers
    t_rel, r_rel = metrics.rel_errors(rows)
    if len(rows) == 0:
        notes.append(
            f"path is {path_len:.1f} m, shorter than the devkit's shortest 100 m segment: t_rel/r_rel unavailable"
            if path_len <= metrics.SEGMENT_LENGTHS[0] else "no complete 100 m segment: t_rel/r_rel unavailable"
        )
    consecutive = np.nonzero(np.diff(ids) == 1)[0]  # RPE only between frames that are really adjacent
    if len(consecutive) == 0:
        notes.append("no two poses are on adjacent ground-truth frames: RPE unavailable")
    gt_m = gt_rel[ids]
    rpe_t, rpe_r = metrics.rpe_from_motions(
        relative(gt_m[consecutive], gt_m[consecutive + 1]), relative(aligned[consecutive], aligned[consecutive + 1])
    )
    return SequenceResult(
        name=name,
        frames=len(est),
        path_length_m=path_len,
        t_rel=None if math.isnan(t_rel) else t_rel,
        r_rel=None if math.isnan(r_rel) else r_rel,
        ate=metrics.ate_rmse(gt_m, aligned),
        rpe_t=rpe_t,
        rpe_r=rpe_r,
        segments=len(rows),
        scale=scale,
        notes=notes,
        segment_rows=rows,
        gt_poses=gt_m,
        est_poses=aligned,
    )


def evaluate_files(pairs: list[tuple[Path, Path]], align: str = "none", per_sequence: bool = False) -> EvalReport:
    """Evaluate (gt_file, est_file) pairs; sequence names are the estimate file stems
    (`per_sequence`: pairs from folders, `EvalReport.per_sequence`)."""
    results = []
    for gt_path, est_path in pairs:
        gt = read_poses(gt_path)
        est = read_poses(est_path)
        results.append(evaluate(gt, est, align=align, name=Path(est_path).stem, est_name=est_path, gt_name=gt_path))
    return EvalReport(results, align, per_sequence)


def pair_result_files(gt: Path, est: Path) -> tuple[list[tuple[Path, Path]], list[str]]:
    """Files pair with files; folders pair by file name (KITTI `NN.txt`), as the devkit does, and
    an estimate without a ground-truth file of its name (KITTI 11-21 have none) is left out and
    named in the second list; a folder with no pair at all is an error."""
    if gt.is_dir() != est.is_dir():
        kinds = lambda p: "a folder" if p.is_dir() else "a file"  # noqa: E731
        raise D3LVOInputError(est, f"is {kinds(est)} but --gt {gt} is {kinds(gt)}: --gt and --est must both be "
                                   "files or both be folders")
    if not gt.is_dir():
        return [(gt, est)], []
    est_files = sorted(est.glob("*.txt"))
    if not est_files:
        raise D3LVOInputError(est, "folder holds no .txt trajectories")
    pairs = [(gt / f.name, f) for f in est_files if (gt / f.name).is_file()]
    unpaired = [f.name for f in est_files if not (gt / f.name).is_file()]
    if not pairs:
        raise D3LVOInputError(gt, f"holds no ground truth of the names in {est} ({', '.join(unpaired[:5])})")
    return pairs, unpaired
