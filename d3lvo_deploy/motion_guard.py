"""The motion guard: a car cannot change its speed by metres per second between two frames.

Where vehicles fill the view, a direct solve that starts at the right motion can slide to the
minimum of a vehicle moving with the camera and report a step a fraction of the last one (0.97 m,
then 0.16 m, 0.1 s later: a deceleration of 81 m/s^2). The next pair then starts from that step.
Where the camera's speed changes by more than `max_accel` times the time between the frames, the
guard keeps the previous motion instead (constant velocity): the step is physically impossible,
whatever fitted the images best. Off by default (`d3lvo run --max-accel A` turns it on, for either
method): it lowers the classical tracker's error on most traffic drives and raises it on others,
where it holds on to a motion that was already wrong, and moves the network's both ways
(docs/evaluation.md, "The motion guard").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import axis_angle_to_rot, rot_to_axis_angle

# m/s^2: the limit chosen on the validation drives (docs/evaluation.md); hard braking is 8-10
CHOSEN_MAX_ACCEL = 30.0


@dataclass(frozen=True)
class MotionGuard:
    # m/s^2 of change in the camera's speed between two frames beyond which a step is replaced by
    # the previous motion; 0 (the default) turns the guard off, CHOSEN_MAX_ACCEL is the measured one
    max_accel: float = 0.0
    # seconds between frames where no timestamps are given (10 Hz, KITTI's rate)
    period: float = 0.1

    @property
    def enabled(self) -> bool:
        return self.max_accel > 0

    def interval(self, before: float | None, after: float | None) -> float:
        """The time between two frames' stamps, or `period` where either is missing."""
        if before is None or after is None or not after > before:
            return self.period
        return float(after - before)


def scaled_motion(A: np.ndarray, factor: float) -> np.ndarray:
    """The rigid motion A (4x4) at constant velocity over `factor` times its time: rotation angle
    and translation scaled; A itself within a thousandth of a factor of 1, where the two times
    differ by their rounding only (seconds since 1970 as a float resolve 0.2 us: a ROS stamp's
    ratio to the last is 1 +- 5e-6 at 10 Hz), so that a recording's format does not move its poses."""
    if abs(factor - 1.0) < 1e-3:
        return np.array(A, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = axis_angle_to_rot(rot_to_axis_angle(A[:3, :3]) * factor)
    out[:3, 3] = np.asarray(A[:3, 3], dtype=np.float64) * factor
    return out


def speed_change(A: np.ndarray, dt: float, previous: np.ndarray, previous_dt: float) -> float:
    """|v - v_previous| in m/s of two frame-to-frame motions (4x4) over dt and previous_dt seconds."""
    return abs(float(np.linalg.norm(A[:3, 3])) / dt - float(np.linalg.norm(previous[:3, 3])) / previous_dt)


def guard_motion(A: np.ndarray, dt: float, previous: np.ndarray | None, previous_dt: float,
                 guard: MotionGuard) -> tuple[np.ndarray, bool]:
    """(the motion to keep, whether the guard replaced A): A where the speed changes by at most
    `guard.max_accel` x dt against the previous kept motion (or there is none, or the guard is
    off), else the previous motion at constant velocity over dt."""
    if not guard.enabled or previous is None or speed_change(A, dt, previous, previous_dt) <= guard.max_accel * dt:
        return A, False
    return scaled_motion(previous, dt / previous_dt), True
