"""Model configuration: what a checkpoint and an export manifest carry to rebuild the network."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

INPUT_MODES = ("rgb", "rgb_sparse", "rgb_completion")
COMPLETIONS = ("learned", "ipbasic")


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

    # depth completion (PENet-style two branches + residual refinement)
    completion_widths: tuple[int, ...] = (16, 32, 64)

    # feature pyramid: levels h/2, h/4, h/8, h/16
    rgb_widths: tuple[int, int, int, int] = (16, 32, 64, 96)
    depth_widths: tuple[int, int, int, int] = (8, 16, 32, 48)
    feature_widths: tuple[int, int, int, int] = (16, 32, 64, 96)
    ca_reduction: int = 4
    xa_levels: tuple[int, ...] = (3,)  # cross attention only at h/16: token count grows 4x per level
    xa_dim: int = 32

    # cost volume, flow and pose
    search_range: int = 4  # S: (2S+1)^2 = 81 displacements
    correlation: str = "slices"  # slices | stacked: two standard-op formulations, same numbers
    flow_levels: tuple[int, ...] = (3, 2, 1)  # coarse to fine; level 0 (h/2) optional
    cost_width: int = 64
    flow_hidden: tuple[int, int] = (128, 64)  # F: 1x1 convs (128, 64, 2) with BN + LeakyReLU
    depth_gate_width: int = 32  # G(D): expand to 32 channels, then 1x1 conv + activation
    context: bool = True
    pose_hidden: tuple[int, int, int] = (256, 128, 64)
    pose_pool: tuple[int, int] = (2, 6)
    dropout: float = 0.2

    def __post_init__(self) -> None:
        if self.mode not in INPUT_MODES:
            raise ValueError(f"mode must be one of {INPUT_MODES}, not {self.mode!r}")
        if self.completion not in COMPLETIONS:
            raise ValueError(f"completion must be one of {COMPLETIONS}, not {self.completion!r}")
        if self.height % 16 or self.width % 16:
            raise ValueError(f"input {self.width}x{self.height} must be divisible by 16 (4 pyramid levels)")
        if list(self.flow_levels) != sorted(self.flow_levels, reverse=True) or not self.flow_levels:
            raise ValueError("flow_levels must run coarse to fine, e.g. (3, 2, 1)")
        if any(not 0 <= lvl <= 3 for lvl in (*self.flow_levels, *self.xa_levels)):
            raise ValueError("pyramid levels are 0..3")

    @property
    def uses_depth(self) -> bool:
        return self.mode != "rgb"

    @property
    def learned_completion(self) -> bool:
        return self.mode == "rgb_completion" and self.completion == "learned"

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
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    @classmethod
    def small(cls, **kw) -> "D3LVOConfig":
        """The CPU-trainable preset for the bundled model: half resolution, narrower layers."""
        base = dict(height=176, width=608, completion_widths=(8, 16, 32), rgb_widths=(12, 24, 48, 64),
                    depth_widths=(8, 12, 24, 32), feature_widths=(12, 24, 48, 64), cost_width=48,
                    flow_hidden=(64, 32), pose_hidden=(256, 128, 64), flow_levels=(3, 2, 1))
        base.update(kw)
        return cls(**base)
