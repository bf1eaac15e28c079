"""Model configuration: what a checkpoint and an export manifest carry to rebuild the network."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

INPUT_MODES = ("rgb", "rgb_sparse", "rgb_completion")
COMPLETIONS = ("learned", "ipbasic")


# the point solver's pyrDown levels at most: frame t's image at the coarsest must still hold a
# gradient and a bilinear sample around every point (a level under ~10 pixels did not)
MAX_PYRAMID_LEVELS = 5
# Gauss-Newton settings that have no weights: the same weights can be exported (`d3lvo export
# --set`) or trained on (`d3lvo train --set`, also on --resume) with other values
SOLVER_KEYS = ("gn_points", "gn_iters", "gn_huber", "gn_damping", "gn_lidar_pool", "pt_iters", "pt_stop", "pt_damping",
               "pt_capacity", "pt_min_gradient", "pt_conf_power", "pt_gate", "pt_conf_full", "pt_scale_every", "pt_median_stride",
               "pt_refine", "pt_affine", "pt_fine_restart", "pt_restart_depth", "pt_scan_gate", "pt_select", "pt_select_rotation", "pt_select_unexplained",
               "pt_select_scan", "pt_select_scan_pass", "pt_select_share", "pt_classical_chain",
               "pt_select_hold")


def check_solver_settings(settings: dict) -> None:
    """Refuse `--set` keys that are not solver settings (they would change weights' meaning), and
    values of another kind than the setting's (a word for a number); ranges are `D3LVOConfig`'s."""
    from d3lvo_deploy.config_values import describe, fits
    from d3lvo_deploy.errors import D3LVOInputError

    bad = sorted(set(settings) - set(SOLVER_KEYS))
    if bad:
        raise D3LVOInputError(None, f"--set takes solver settings only ({', '.join(SOLVER_KEYS)}), not {', '.join(bad)}")
    defaults = D3LVOConfig()
    for key, value in settings.items():
        default = getattr(defaults, key)
        # one number for a per-level setting: `D3LVOConfig` then says how many it takes
        one = isinstance(default, tuple) and not isinstance(value, tuple)
        if not fits((value,) if one else value, default):
            what = describe(default) + (" separated by commas" if isinstance(default, tuple) else "")
            joined = ",".join(str(v) for v in value) if isinstance(value, tuple) else str(value)
            raise D3LVOInputError(None, f"--set {key}={joined}: {key} takes {what}")


MIN_INPUT = 32  # pixels a side: h/16, the coarsest level, keeps at least two cells


def input_size_problem(height, width) -> str | None:
    """What is wrong with a network input size, or None: whole pixels, at least MIN_INPUT a side,
    divisible by 16 (four pyramid levels halve it)."""
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (height, width)):
        return f"input size {width!r}x{height!r} must be whole numbers of pixels"
    if height < MIN_INPUT or width < MIN_INPUT:
        return f"input {width}x{height} is too small: at least {MIN_INPUT}x{MIN_INPUT}"
    if height % 16 or width % 16:
        return f"input {width}x{height} must be divisible by 16 (4 pyramid levels)"
    return None


@dataclass
class D3LVOConfig:
    # input (paper: 1216x352 bottom-centre crop of image_2; `scale` resizes it for cheaper models)
    height: int = 352
    width: int = 1216
    mode: str = "rgb_completion"  # rgb | rgb_sparse | rgb_completion (the paper's ablation rows)
    completion: str = "learned"  # learned (PENet-style) | ipbasic (classical, no parameters)
    rgb_mean: tuple[float, float, float] = (0.485, 0.456, 0.406)
    rgb_std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    min_depth: float = 0.5  # m; depth enters the network as min_depth / depth in (0, 1], holes as 0
    max_depth: float = 120.0

    # Widths and levels are the realtime default: 10 Hz at 1216x352 on 2 CPU cores with
    # onnxruntime (`d3lvo bench`). Channel counts are multiples of 16 where it matters (onnxruntime's
    # blocked conv kernels run 3-6x more multiply-adds per second at 16/32 channels than at 8/12/24).

    # depth completion (PENet-style two branches + residual refinement; h/2..h/8, output via h/4)
    completion_widths: tuple[int, int, int] = (8, 16, 32)

    # feature pyramid: levels h/2, h/4, h/8, h/16 (conv + residual block each)
    rgb_widths: tuple[int, int, int, int] = (16, 16, 32, 64)
    depth_widths: tuple[int, int, int, int] = (8, 16, 16, 32)
    feature_widths: tuple[int, int, int, int] = (16, 32, 32, 64)
    ca_reduction: int = 4
    xa_levels: tuple[int, ...] = (3,)  # cross attention only at h/16: token count grows 4x per level
    xa_dim: int = 16

    # cost volume, flow and pose
    search_range: int = 4  # S: (2S+1)^2 = 81 displacements
    correlation: str = "tiled"  # tiled | slices | stacked: standard-op formulations, same numbers
    # coarse to fine. h/16 + h/8 is the realtime default; adding h/4 (3, 2, 1) costs ~35 ms per
    # frame at 1216x352 on 2 cores (cost volume, warp and context net at 26.7k pixels)
    flow_levels: tuple[int, ...] = (3, 2)
    cost_width: int = 32
    flow_hidden: tuple[int, int] = (128, 64)  # F: 1x1 convs (128, 64, 2) with BN + LeakyReLU (paper)
    depth_gate_width: int = 32  # G(D): expand to 32 channels, then 1x1 conv + activation (paper)
    context: bool = True
    context_width: int = 16
    # P (eq. 8-9): "gauss_newton" (default) solves dT by a weighted Gauss-Newton step on SE(3):
    # frame t-1's pixels, back-projected with the level's dense depth, are moved by T and compared
    # with frame t's features (photometric + learned channels, PixLoc / DVL-SLAM style) under
    # per-pixel confidences the network predicts; "mlp" is the paper's regression head; "auto"
    # takes gauss_newton where the mode has depth and mlp for rgb (nothing to back-project).
    # "points" (the bundled model's): the classical direct tracker on frame t-1's LiDAR point list
    # at the camera's own resolution, each point weighted by a learned confidence that it does not
    # move (models/pose_points.py); with confidence 1 it is `d3lvo run --method direct`
    pose_head: str = "auto"
    # the point solver (pose_head="points"); the defaults are d3lvo_deploy.direct.DirectConfig's and
    # d3lvo_deploy.points.PointConfig's, so that the network's classical mode is the direct tracker
    pt_iters: tuple[int, ...] = (15, 15, 15)  # most Gauss-Newton steps per pyrDown level, coarse to fine
    pt_stop: float = 1e-6
    pt_damping: float = 1e-4
    # the Huber threshold is taken from the residuals' median at every this-th step of a level and
    # kept in between (the median is a partial sort, the dearest node of a step on OpenVINO)
    pt_scale_every: int = 3
    # that median over every this-th point of the list only (points are in scan order, so the
    # sample spreads over the view): the partial sort's time grows with its length, and a robust
    # scale does not need every point (docs/performance.md)
    pt_median_stride: int = 1
    # after the finest level, every point the solved pose explains (residual within the Huber
    # threshold) weighs fully again, and up to this many more steps are taken there: the confidence
    # is read before the pose is known, and on a static scene its doubts only reweight good points
    pt_refine: int = 0
    # match frame t's grey to frame t-1's mean and spread at every Gauss-Newton step (both
    # solves): an exposure change shifts every residual alike, and without the match the solve
    # can trade it for motion (docs/evaluation.md)
    pt_affine: bool = False
    # above 0: also solve the finest level alone from the start (both solves), and keep that pose
    # where it explains the points better by more than this (`point_solver.consensus_gain`): a
    # coarse level can hold a wrong minimum (docs/evaluation.md)
    pt_fine_restart: float = 0.0
    # above 0 (and pt_fine_restart too; with it 0 there is no restart to check): the flow+pose
    # graph also takes frame t's LiDAR depth at the camera's resolution (`scan_depth2`), and the
    # restart is also kept where its depth error against that scan is below this times the
    # coarse-to-fine pose's (`point_solver.lidar_depth_error`): the scan sees a forward step the
    # photometric costs can miss (docs/evaluation.md). Training solves without it: its samples
    # carry no scan, and the check picks between two poses without a gradient
    pt_restart_depth: float = 0.0
    # above 0: the flow+pose graph also takes frame t's LiDAR depth (`scan_depth2`), and before
    # each solve (both) the points of frame t-1 that it puts more than this (relative depth) from
    # where the starting motion moves them get weight 0 (`point_solver.scan_kept`): what moved, before the
    # solve can follow it (docs/evaluation.md). The choice between the two poses (pt_select ...)
    # reads the confidence's weights, not gated. Training solves without it, as for pt_restart_depth
    pt_scan_gate: float = 0.0
    pt_capacity: int = 2048  # length of the point list (the graph's fixed input size)
    pt_min_gradient: float = 0.02
    # a point's weight is its confidence to this power: 1 keeps the trained probability; higher
    # powers push what is likely moving further down while static points (confidence ~0.9) keep
    # most of their weight; confidence 1 stays weight 1, the classical tracker
    pt_conf_power: float = 1.0
    # above 0: a point's weight is 1 where its confidence exceeds this, else 0 (what the network
    # thinks likely moves is dropped, the rest is tracked exactly as the classical tracker does)
    pt_gate: float = 0.0
    # a static prior: a point weighs fully once its confidence reaches this, and conf / pt_conf_full
    # below it; the solver then tracks the scene exactly as the classical tracker does wherever
    # the network is not fairly sure something moves. 1: the weight is the confidence itself
    pt_conf_full: float = 1.0
    # above 0: the classical solve (every weight 1) runs beside the weighted one, and its pose is
    # kept unless the weighted pose explains the points the network trusts better by more than
    # this (the mean MSAC cost per point, `point_solver.consensus_gain`): on a static scene the
    # classical pose, fitted to every point at full weight, is the better estimate, and only
    # something that moves pulls it off the static points. 0: the weighted pose always
    pt_select: float = 0.0
    # with pt_select, the weighted pose is kept only where its rotation also differs from the
    # classical one's by more than this many degrees: below it the two are the same solution up
    # to the solver's noise, and the classical one, fitted to every point, has the lower variance.
    # 0: off; with pt_select 0 (the weighted pose always) it has nothing to gate (docs/model-card.md,
    # chosen on validation drives)
    pt_select_rotation: float = 0.0
    # with pt_select, the weighted pose is kept only where the confidence, read again with the
    # classical pose as the motion its evidence is measured against, still distrusts more than
    # this share of frame t-1's points (weight under 0.5): where the classical pose leaves nothing
    # unexplained, the weighted one had only doubted a poor start. 0: off (docs/model-card.md)
    pt_select_unexplained: float = 0.0
    # with pt_select, frame t's own LiDAR scan as a second judge (`scan_depth2`,
    # `point_solver.lidar_depth_error` of the points the network trusts, moved by each pose): above
    # 0, the weighted pose is kept only where its depth error is at most pt_select_scan times the
    # classical pose's; above 0 (at most 1), pt_select_scan_pass keeps it also wherever its error is
    # below this times the classical pose's, whatever the photometric test said. Only where both
    # poses put trusted points on the scan's returns; training's samples carry no scan, so there the
    # photometric test alone decides. The scan does not read the images, so a pose that an exposure
    # change or a moving shadow favours does not fit it better (docs/model-card.md)
    pt_select_scan: float = 0.0
    pt_select_scan_pass: float = 0.0
    # with pt_select, below 1: the photometric test passes only where the network distrusts at most
    # this share of frame t-1's points (weight under 0.5): a confidence that doubts most of the
    # scene has nothing left to tell the motion by, and its gain is its own doubt
    # (`pose_points.distrusted_share`; the scan's pass is not capped). 1: off (docs/model-card.md)
    pt_select_share: float = 1.0
    # with pt_select: the classical solve starts each pair from the previous classical pose (its own
    # constant velocity, as `d3lvo run --method direct` does) instead of the weighted one's; where
    # the classical pose is kept on every pair the run is the classical mode's. The solve creeps
    # (docs/performance.md), so its pose depends on its start: started from the weighted chain, the
    # classical pose kept on a static drive tracked worse than the classical mode's own (graph input
    # `classical_start`, output `classical_next`). Off in the bundled model: no static gain, some
    # traffic lost (docs/model-card.md)
    pt_classical_chain: bool = False
    # with pt_select: the weighted pose also kept on this many pairs after each pair the choice
    # keeps it on (graph output `select_kept`; the runtime holds the count, and a resumed run reads
    # it back from the `.start` file). A vehicle that pulled the classical pose off stays in view
    # for a while, and the evidence that picked the weighted pose on one pair is often just under
    # the thresholds on the next (docs/model-card.md, chosen on validation drives). 0: off
    pt_select_hold: int = 0
    # what the confidence net reads: "evidence", only where the starting motion fails to explain
    # frame t (flow minus rigid flow, the depth, rigid-warp and flow-warp residuals) and the inverse
    # depth; "all" adds the flow estimator's state and frame t-1's features, from which it also
    # learns what moving things look like and where they tend to be (docs/model-card.md)
    pt_conf_inputs: str = "all"
    gn_iters: int = 4  # Gauss-Newton iterations per level (unrolled in the graph)
    gn_extra_levels: tuple[int, ...] = (1,)  # levels finer than the flow's with a Gauss-Newton step, no flow
    gn_features: int = 8  # learned feature channels beside the grey image in the residual
    gn_huber: float = 0.1  # Huber threshold on the residual (normalised-RGB units)
    gn_damping: float = 1e-3  # Levenberg-Marquardt lambda (relative to diag(H))
    # which cells of frame t-1 the solver back-projects: "lidar", those whose pixel has a LiDAR
    # return (exact depth), or "dense", every cell with the completed depth. Measured on the
    # held-out 09-motion drive, same weights (a run trained with every cell, step 300; README):
    # t_rel 1.07 % (lidar) vs 13.48 % (dense)
    gn_points: str = "lidar"
    # with gn_points="lidar", which return a cell gets: "stride", the one exactly on the cell's
    # pixel s*i (none if that pixel has none), or "nearest", the closest return within half a cell
    # of it (a max-pool of inverse depth centred on s*i: up to s^2 times the points at level s, each
    # with the depth of a return up to s/2 pixels away). Measured on the held-out 09-motion drive,
    # same weights (step 1,800, README): t_rel 0.83 -> 0.77 %, r_rel 0.95 -> 0.77 deg/100m
    gn_lidar_pool: str = "nearest"
    pose_hidden: tuple[int, int, int] = (256, 128, 64)  # P: the paper's MLP
    pose_width: int = 32  # the two strided convs before the pose MLP
    pose_pool: tuple[int, int] = (2, 6)
    dropout: float = 0.2

    def __post_init__(self) -> None:
        problem = input_size_problem(self.height, self.width)
        if problem:
            raise ValueError(problem)
        if self.mode not in INPUT_MODES:
            raise ValueError(f"mode must be one of {INPUT_MODES}, not {self.mode!r}")
        if self.completion not in COMPLETIONS:
            raise ValueError(f"completion must be one of {COMPLETIONS}, not {self.completion!r}")
        if list(self.flow_levels) != sorted(self.flow_levels, reverse=True) or not self.flow_levels:
            raise ValueError("flow_levels must run coarse to fine, e.g. (3, 2, 1)")
        if any(not 0 <= lvl <= 3 for lvl in (*self.flow_levels, *self.xa_levels)):
            raise ValueError("pyramid levels are 0..3")
        if len(self.completion_widths) != 3:
            raise ValueError("completion_widths needs 3 values (h/2, h/4, h/8)")
        # layer widths: so many channels per level, each a whole number above 0 (a layer of 0 or
        # -32 channels would otherwise fail inside torch, in a traceback)
        for key, count in (("completion_widths", 3), ("rgb_widths", 4), ("depth_widths", 4), ("feature_widths", 4),
                           ("flow_hidden", 2), ("pose_hidden", None)):  # the MLP: any number of layers
            widths = getattr(self, key)
            if (len(widths) != count if count else not widths) or not all(
                    isinstance(w, int) and not isinstance(w, bool) and w >= 1 for w in widths):
                raise ValueError(f"{key} takes {count or 'one or more'} channel counts, each a whole number of 1 or "
                                 f"more, not {list(widths)}")
        for key in ("ca_reduction", "xa_dim", "cost_width", "depth_gate_width", "context_width"):
            if not (isinstance(getattr(self, key), int) and getattr(self, key) >= 1):
                raise ValueError(f"{key} must be a whole number of 1 or more, not {getattr(self, key)!r}")
        if not (isinstance(self.search_range, int) and self.search_range >= 1):
            raise ValueError(f"search_range must be a whole number of 1 or more, not {self.search_range!r}")
        if self.pose_head not in ("auto", "gauss_newton", "mlp", "points"):
            raise ValueError(f"pose_head must be auto, gauss_newton, mlp or points, not {self.pose_head!r}")
        if self.pose_head in ("gauss_newton", "points") and not self.uses_depth:
            raise ValueError(f"pose_head {self.pose_head} needs depth (LiDAR points); use pose_head=mlp with mode rgb")
        if any(not 0 <= lvl <= 3 for lvl in self.gn_extra_levels):
            raise ValueError("gn_extra_levels are pyramid levels 0..3")
        if self.gn_points not in ("lidar", "dense"):
            raise ValueError(f"gn_points must be lidar or dense, not {self.gn_points!r}")
        if self.gn_lidar_pool not in ("stride", "nearest"):
            raise ValueError(f"gn_lidar_pool must be stride or nearest, not {self.gn_lidar_pool!r}")
        if not (isinstance(self.pt_iters, (tuple, list)) and self.pt_iters
                and all(isinstance(n, int) and n >= 1 for n in self.pt_iters)):
            raise ValueError(f"pt_iters takes one step count per pyramid level, e.g. 15,15,15, not {self.pt_iters!r}")
        if len(self.pt_iters) > MAX_PYRAMID_LEVELS:
            raise ValueError(f"pt_iters: at most {MAX_PYRAMID_LEVELS} pyramid levels, not {len(self.pt_iters)} (each "
                             "level halves the camera image: a sixth leaves KITTI's 1242x375 at 38x11 pixels)")
        # the solver's numbers: a negative damping or stop makes the step's solve meaningless
        for key in ("pt_stop", "pt_damping", "pt_min_gradient", "gn_damping"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{key} must be 0 or more, not {getattr(self, key)!r}")
        if not self.gn_huber > 0:
            raise ValueError(f"gn_huber must be above 0, not {self.gn_huber!r}")
        if not (isinstance(self.gn_iters, int) and self.gn_iters >= 0):
            raise ValueError(f"gn_iters must be a whole number of steps, 0 or more, not {self.gn_iters!r}")
        if not (isinstance(self.pt_scale_every, int) and self.pt_scale_every >= 1):
            raise ValueError(f"pt_scale_every must be a whole number of steps, at least 1, not {self.pt_scale_every!r}")
        if not (isinstance(self.pt_median_stride, int) and self.pt_median_stride >= 1):
            raise ValueError(f"pt_median_stride must be a whole number of points, at least 1, not {self.pt_median_stride!r}")
        if not isinstance(self.pt_affine, bool):
            raise ValueError(f"pt_affine must be true or false, not {self.pt_affine!r}")
        if not (isinstance(self.pt_fine_restart, (int, float)) and 0 <= self.pt_fine_restart < 1):
            raise ValueError(f"pt_fine_restart must be in [0, 1) (0: off), not {self.pt_fine_restart!r}")
        if not (isinstance(self.pt_restart_depth, (int, float)) and 0 <= self.pt_restart_depth <= 1):
            raise ValueError(f"pt_restart_depth must be in [0, 1] (0: off), not {self.pt_restart_depth!r}")
        if not (isinstance(self.pt_scan_gate, (int, float)) and 0 <= self.pt_scan_gate <= 1):
            raise ValueError(f"pt_scan_gate must be in [0, 1] (0: off), not {self.pt_scan_gate!r}")
        if not (isinstance(self.pt_refine, int) and self.pt_refine >= 0):
            raise ValueError(f"pt_refine must be a whole number of steps, 0 or more, not {self.pt_refine!r}")
        if not (isinstance(self.pt_capacity, int) and self.pt_capacity >= 12):
            raise ValueError(f"pt_capacity must be a whole number of points, at least 12, not {self.pt_capacity!r}")
        if not (isinstance(self.pt_conf_power, (int, float)) and self.pt_conf_power > 0):
            raise ValueError(f"pt_conf_power must be above 0, not {self.pt_conf_power!r}")
        if not (isinstance(self.pt_gate, (int, float)) and 0 <= self.pt_gate < 1):
            raise ValueError(f"pt_gate must be in [0, 1), not {self.pt_gate!r}")
        if not (isinstance(self.pt_select, (int, float)) and 0 <= self.pt_select < 1):
            raise ValueError(f"pt_select must be in [0, 1) (0: off), not {self.pt_select!r}")
        if not (isinstance(self.pt_select_rotation, (int, float)) and 0 <= self.pt_select_rotation < 90):
            raise ValueError(f"pt_select_rotation must be in [0, 90) degrees (0: off), not {self.pt_select_rotation!r}")
        if not (isinstance(self.pt_select_unexplained, (int, float)) and 0 <= self.pt_select_unexplained < 1):
            raise ValueError(f"pt_select_unexplained must be a share in [0, 1) (0: off), not {self.pt_select_unexplained!r}")
        if not (isinstance(self.pt_select_scan, (int, float)) and 0 <= self.pt_select_scan < 100):
            raise ValueError(f"pt_select_scan must be a ratio of depth errors in [0, 100) (0: off), not {self.pt_select_scan!r}")
        if not (isinstance(self.pt_select_scan_pass, (int, float)) and 0 <= self.pt_select_scan_pass <= 1):
            raise ValueError("pt_select_scan_pass must be a ratio of depth errors in [0, 1] (0: off; above 1 it "
                             f"would keep a weighted pose that fits the scan worse), not {self.pt_select_scan_pass!r}")
        if not (isinstance(self.pt_select_share, (int, float)) and 0 < self.pt_select_share <= 1):
            raise ValueError(f"pt_select_share must be a share in (0, 1] (1: off), not {self.pt_select_share!r}")
        if not isinstance(self.pt_classical_chain, bool):
            raise ValueError(f"pt_classical_chain must be true or false, not {self.pt_classical_chain!r}")
        if self.pt_classical_chain and not (self.point_solver and self.pt_select > 0):
            raise ValueError("pt_classical_chain needs a point solver that also solves its classical mode (pt_select "
                             "above 0): without it there is no classical solve to start")
        if not (isinstance(self.pt_select_hold, int) and not isinstance(self.pt_select_hold, bool)
                and 0 <= self.pt_select_hold <= 1000):
            raise ValueError(f"pt_select_hold must be a whole number of pairs in 0..1000 (0: off), not {self.pt_select_hold!r}")
        if self.pt_select_hold and not (self.point_solver and self.pt_select > 0):
            raise ValueError("pt_select_hold needs a point solver that chooses between its weighted and classical "
                             "poses (pt_select above 0): without the choice there is nothing to hold")
        if self.pt_conf_inputs not in ("all", "evidence"):
            raise ValueError(f"pt_conf_inputs must be all or evidence, not {self.pt_conf_inputs!r}")
        if not (isinstance(self.pt_conf_full, (int, float)) and 0 < self.pt_conf_full <= 1):
            raise ValueError(f"pt_conf_full must be in (0, 1], not {self.pt_conf_full!r}")
        if self.correlation not in ("tiled", "slices", "stacked"):
            raise ValueError(f"correlation must be tiled, slices or stacked, not {self.correlation!r}")

    @property
    def uses_depth(self) -> bool:
        return self.mode != "rgb"

    @property
    def learned_completion(self) -> bool:
        return self.mode == "rgb_completion" and self.completion == "learned"

    @property
    def geometric(self) -> bool:
        """The Gauss-Newton head on the network's cells."""
        return self.pose_head == "gauss_newton" or (self.pose_head == "auto" and self.uses_depth)

    @property
    def point_solver(self) -> bool:
        """The direct solver on the LiDAR point list under a learned confidence."""
        return self.pose_head == "points"

    @property
    def checks_restart_on_scan(self) -> bool:
        """The solver checks the finest level's restart against frame t's LiDAR depth."""
        return (self.point_solver and self.pt_fine_restart > 0 and self.pt_restart_depth > 0
                and len(self.pt_iters) > 1)

    @property
    def reads_scan(self) -> bool:
        """The flow+pose graph takes frame t's LiDAR depth (`scan_depth2`): for the restart's check,
        to gate the points before the solve, or to judge between the weighted and the classical pose."""
        return self.checks_restart_on_scan or self.gates_on_scan or (
            self.point_solver and self.pt_select > 0 and (self.pt_select_scan > 0 or self.pt_select_scan_pass > 0))

    @property
    def gates_on_scan(self) -> bool:
        """Both solves drop the points frame t's scan puts elsewhere (`pt_scan_gate`)."""
        return self.point_solver and self.pt_scan_gate > 0

    @property
    def gn_levels(self) -> tuple[int, ...]:
        """Levels with a Gauss-Newton step, coarse to fine (none for the mlp head): the flow levels,
        then those of `gn_extra_levels` finer than the finest flow level."""
        if not self.geometric:
            return ()
        extra = sorted((lvl for lvl in set(self.gn_extra_levels) if lvl < min(self.flow_levels)), reverse=True)
        return (*self.flow_levels, *extra)

    @property
    def gn_lidar(self) -> bool:
        """Whether the solver reads the LiDAR returns themselves (an input beside the completed
        depth): with learned completion; rgb_sparse's depth is the LiDAR already, IP-Basic's is dense."""
        return self.geometric and self.gn_points == "lidar" and self.learned_completion

    @property
    def depth_levels(self) -> tuple[int, ...]:
        """Levels at which the encoder returns frame depth."""
        return tuple(sorted(set(self.flow_levels) | set(self.gn_levels), reverse=True))

    @property
    def depth_input(self) -> str:
        """What the data pipeline must feed as depth: none, sparse LiDAR, or IP-Basic dense depth."""
        if self.mode == "rgb":
            return "none"
        if self.mode == "rgb_completion" and self.completion == "ipbasic":
            return "ipbasic"
        return "sparse"

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "D3LVOConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config keys {sorted(unknown)}")
        d = dict(d)
        d.setdefault("pose_head", "mlp")  # configs written before the Gauss-Newton head had the MLP
        d.setdefault("gn_points", "dense")  # and before gn_points, the solver used every cell
        d.setdefault("gn_lidar_pool", "stride")  # and before gn_lidar_pool, only returns on a cell's pixel
        d.setdefault("pt_scale_every", 1)  # and before pt_scale_every, the Huber threshold at every step
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    @classmethod
    def paper(cls, **kw) -> "D3LVOConfig":
        """The network as the paper sizes it, for GPU training: 1216x352, flow at all four pyramid
        levels h/16..h/2 (Sec. III-C), the MLP pose head P (256, 128, 64) with hierarchical
        refinement and eq. 10's learned level weights, a PWC-Net-like pyramid (16, 32, 64, 96
        channels; the paper builds on PWC-Net without giving widths) and wider PENet-style
        completion. Cross attention stays at h/16: the paper gives no level, and its token count
        grows 4x per finer level (`python -m models.stats` prints params and FLOPs)."""
        base = dict(height=352, width=1216, flow_levels=(3, 2, 1, 0), pose_head="mlp",
                    completion_widths=(32, 64, 128), rgb_widths=(16, 32, 64, 96), depth_widths=(16, 32, 64, 96),
                    feature_widths=(16, 32, 64, 96), cost_width=64, context_width=32)
        base.update(kw)
        return cls(**base)

    @classmethod
    def preset(cls, name: str, **kw) -> "D3LVOConfig":
        """default (the realtime network at 1216x352) | small (608x176, the bundled model's) | paper."""
        makers = {"default": cls, "small": cls.small, "paper": cls.paper}
        if name not in makers:
            raise ValueError(f"preset must be one of {', '.join(makers)}, not {name!r}")
        return makers[name](**kw)

    @classmethod
    def small(cls, **kw) -> "D3LVOConfig":
        """The default network at half resolution (608x176), what the bundled model is trained at
        (2 CPU cores train it ~4x faster), with the h/4 flow level added: its finest flow grid is
        then 152x44 cells, the same as the default's h/8 at 1216x352. At h/8 of 608x176 a typical
        frame-to-frame rotation of 0.5 deg moves the image by ~0.4 cells, and a first training
        run with flow at h/16 + h/8 here did not learn rotation at all."""
        base = dict(height=176, width=608, flow_levels=(3, 2, 1), gn_extra_levels=(0,))
        base.update(kw)
        return cls(**base)
