"""What a calibration session is asked to do, and what it keeps of each pose."""
from __future__ import annotations

from dataclasses import dataclass, field

from imubench.procedures.poses import Targets


@dataclass
class Tolerances:
    accel_rms_mg: float = 1.0        # RMS of |a| - g over the poses after calibration
    verify_mg: float = 2.0           # each verification pose: | |a| - g | of the device's output
    gyro_turntable_rms_dps: float = 0.1
    gyro_rotation_rms_deg: float = 0.5


@dataclass
class SessionConfig:
    method: str = "six"              # "six" | "multi"
    gyro: str | None = "bias"        # a live method of calib.fit.GYRO_METHODS, or None
    rate_hz: int = 500
    rest_s: float = 5.0              # still at the start: noise and gyro bias
    settle_s: float = 0.5            # still this long before a pose is captured
    hold_s: float = 2.0              # captured per pose
    pose_timeout_s: float | None = 120.0   # waiting for an attitude, in device time; None: wait
    turntable_rates_dps: tuple = (30.0, 90.0)
    turntable_s: float = 3.0
    verify_poses: int = 3
    write: bool = True               # write the parameters back if the fit passes
    note: str = ""
    tolerances: Tolerances = field(default_factory=Tolerances)
    # adaptive capture (procedures.poses.Targets): each attitude held until its |a| is known to
    # targets.pose_sigma_mg; a multi-position session stops adding attitudes when every
    # parameter's sigma is at its target. False: hold_s per attitude, every planned attitude.
    adaptive: bool = False
    targets: Targets = field(default_factory=Targets)


@dataclass
class PoseRecord:
    name: str
    direction: list                  # planned gravity direction in the board frame
    mean_mps2: list                  # measured mean specific force (nominal scaling)
    sigma_mean_mps2: list            # 1-sigma of that mean
    n: int
    start_index: int                 # sample_index of the first sample used
    stop_index: int
    temp_c: float
    gyro_mean_rad_s: list
    stream: int = 0                  # which continuous stream (capture-<stream>.bin) it is in
    sigma_norm_g: float | None = None      # 1-sigma of the mean |a| over the hold, g
    angle_from_plan_deg: float | None = None   # measured gravity direction vs the planned one
