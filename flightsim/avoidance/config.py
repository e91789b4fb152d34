"""``[avoidance]``: which simulated autopilot limits the velocity, and its parameters (docs/derivations/sectors.md).

:class:`AvoidanceConfig` is the scenario's ``[avoidance]`` table (``flightsim sitl --avoidance
MODEL`` overrides ``model``); :data:`MODELS` the models :func:`flightsim.avoidance.make_avoidance`
builds; :data:`F450_RADIUS_M` the quad's body radius for contact.
"""

from __future__ import annotations

import dataclasses

from companion.config import require, require_finite

MODELS = ("none", "ardupilot", "px4")
BEHAVES = ("slide", "stop")
#: F450 body radius for contact: 450 mm motor-to-motor diagonal (0.225 m to a motor axis) plus a
#: 10-inch propeller's 0.127 m radius
F450_RADIUS_M = 0.35


@dataclasses.dataclass(frozen=True)
class AvoidanceConfig:
    """``[avoidance]``: which autopilot model limits the quad's velocity, and its parameters.

    Defaults are the shipped defaults of each autopilot, except ``cp_dist_m``: PX4 ships
    ``CP_DIST = −1`` (collision prevention off), so the model needs a distance to do anything.
    """

    model: str = "none"  # "ardupilot", "px4" or "none" (no avoidance; the route must then be clear)
    # ArduPilot Copter (AC_Avoid, AP_Proximity)
    avoid_margin_m: float = 2.0  # AVOID_MARGIN: distance to keep from obstacles, m
    avoid_accel_max_mss: float = 3.0  # AVOID_ACCEL_MAX: limit on how fast avoidance changes the velocity, m/s² (0 = off)
    avoid_behave: str = "slide"  # AVOID_BEHAVE: "slide" (keep the velocity along the obstacle) or "stop"
    avoid_backup_spd_mps: float = 0.75  # AVOID_BACKUP_SPD: speed to back away when inside the margin, m/s (0 = off)
    avoid_backup_dz_m: float = 0.1  # AVOID_BACKUP_DZ: dead zone inside the margin before backing away, m
    pos_kp: float = 1.0  # PSC_POSXY_P: the position controller's gain that shapes the braking curve, 1/s
    prx_filt_hz: float = 0.25  # PRX_FILT: low-pass cut-off on each proximity face, Hz (0 = off)
    face_timeout_s: float = 1.0  # a proximity face not updated for this long is dropped (PROXIMITY_FACE_RESET_MS), s
    # PX4 (CollisionPrevention, multicopter position control)
    cp_dist_m: float = 2.0  # CP_DIST: distance to keep, m (PX4 ships −1 = disabled)
    cp_delay_s: float = 0.4  # CP_DELAY: sensor and tracking delay, s
    cp_guide_ang_deg: float = 30.0  # CP_GUIDE_ANG: how far the setpoint may be turned towards free space, degrees
    cp_go_no_data: bool = False  # CP_GO_NO_DATA: allow moving into directions without data
    mpc_xy_p: float = 0.95  # MPC_XY_P: position gain, 1/s
    mpc_acc_hor_mss: float = 3.0  # MPC_ACC_HOR: horizontal acceleration, m/s²
    mpc_jerk_max_msss: float = 8.0  # MPC_JERK_MAX: jerk limit, m/s³
    # both
    stale_s: float = 0.5  # a sensor (ArduPilot) or bin (PX4) without messages for this long has no data, s

    def __post_init__(self) -> None:
        require(self.model in MODELS, f"avoidance model must be one of {', '.join(MODELS)}, got {self.model!r}")
        require(self.avoid_behave in BEHAVES, f"avoid_behave must be one of {', '.join(BEHAVES)}, got {self.avoid_behave!r}")
        for name in ("avoid_margin_m", "avoid_accel_max_mss", "avoid_backup_spd_mps", "avoid_backup_dz_m", "prx_filt_hz",
                     "cp_delay_s", "cp_guide_ang_deg"):
            require_finite(name, getattr(self, name), nonnegative=True)
        for name in ("pos_kp", "face_timeout_s", "cp_dist_m", "mpc_xy_p", "mpc_acc_hor_mss", "mpc_jerk_max_msss", "stale_s"):
            require_finite(name, getattr(self, name), positive=True)
        require(self.avoid_margin_m <= 10, f"avoid_margin_m must be <= 10 (AVOID_MARGIN range), got {self.avoid_margin_m}")
        require(self.cp_dist_m <= 15, f"cp_dist_m must be <= 15 (CP_DIST range), got {self.cp_dist_m}")
        require(self.cp_delay_s <= 1, f"cp_delay_s must be <= 1 (CP_DELAY range), got {self.cp_delay_s}")
        require(self.cp_guide_ang_deg <= 90, f"cp_guide_ang_deg must be <= 90 (CP_GUIDE_ANG range), got {self.cp_guide_ang_deg}")
        require(isinstance(self.cp_go_no_data, bool), f"cp_go_no_data must be true or false, got {self.cp_go_no_data!r}")


__all__ = ["AvoidanceConfig", "MODELS", "BEHAVES", "F450_RADIUS_M"]
