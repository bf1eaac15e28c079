"""Which vehicles of a rendered drive's traffic run into the camera's own car.

    .venv/bin/python scripts/ego_collisions.py DRIVE...

Plans each drive's traffic again from its `synth.json` (run from the checkout root, where the
`--motion-from` paths it names resolve) and prints, per drive, how many vehicles the plan has
without the check and which kinds `traffic.meets_ego` drops (`d3lvo synth --ego-collisions`
keeps them). A drive that lists none renders the same with and without the check.
"""

from __future__ import annotations

import sys

import numpy as np

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.synth.generator import (DriveConfig, LidarConfig, SynthConfig, make_poses, make_scene,
                                          rendered_settings)
from d3lvo_deploy.synth.traffic import meets_ego, plan_traffic
from d3lvo_deploy.synth.world import build_path


def settings(drive: str) -> SynthConfig:
    """The drive's render settings, as `d3lvo synth` wrote them."""
    written = rendered_settings(drive)
    if written is None:
        raise D3LVOInputError(drive, "no readable synth.json: not a folder `d3lvo synth` rendered")
    written = {k: v for k, v in written.items() if k != "generator_version"}
    try:
        return SynthConfig(**{**written, "lidar": LidarConfig(**written["lidar"]),
                              "drive": DriveConfig(**written["drive"])})
    except (KeyError, TypeError) as e:
        raise D3LVOInputError(drive, f"synth.json does not hold d3lvo synth's settings ({e})") from None


def main(drives: list[str]) -> None:
    for drive in drives:
        cfg = settings(drive)
        if not cfg.traffic:
            print(f"{drive}: no traffic")
            continue
        poses = make_poses(cfg)
        every = plan_traffic(build_path(poses), make_scene(poses, cfg.seed).style, poses, cfg.traffic,
                             np.random.default_rng([cfg.seed, 3]), clear_ego=False)
        hits = [v.kind for v in every if meets_ego(v, poses)]
        print(f"{drive}: {len(every)} vehicles, {len(hits)} run into the camera's car"
              + (f" ({', '.join(hits)})" if hits else ""))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    try:
        main(sys.argv[1:])
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
