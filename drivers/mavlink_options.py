"""The MAVLink link's options and their defaults (the URL's query keys have the same names);
``drivers.mavlink_link.parse_mavlink_url`` reads and checks them. No pymavlink here
(drivers/mavlink_link.py is its only importer)."""

from __future__ import annotations

from dataclasses import dataclass, field

MAV_COMP_ID_VIO = 197

# the messages requested with MAV_CMD_SET_MESSAGE_INTERVAL, and the default rates [Hz], each one
# that ArduPilot Rover grants with its default SCHED_LOOP_RATE of 50 Hz (measured on the SITL build,
# docs/mavlink.md §3: it refuses an interval under 1.25 loop periods, so ATTITUDE at 41 Hz and more).
# Not WHEEL_DISTANCE: ArduPilot has no interval for it (it refuses every request); it streams in
# the EXTRA1 group when wheel encoders are configured, and the link uses it when it comes.
DEFAULT_RATES_HZ: dict[str, float] = {
    "ATTITUDE": 25.0,
    "LOCAL_POSITION_NED": 10.0,
    "SERVO_OUTPUT_RAW": 10.0,
    "RC_CHANNELS": 5.0,
    "SYSTEM_TIME": 1.0,
    "EKF_STATUS_REPORT": 2.0,
}


@dataclass(frozen=True, slots=True)
class MavlinkOptions:
    """Every option of the MAVLink link with its default (URL query keys have the same names)."""

    mode: str = "out"  # udp only: "out" (robotd sends first) or "in" (robotd listens)
    allow_remote: bool = False  # allow mode=in on a non-loopback address
    baud: int = 921600  # serial only
    sysid: int = 0  # 0: use the autopilot's system id (learned from its heartbeat; 1 until then)
    compid: int = MAV_COMP_ID_VIO
    message: str = "odometry"  # or "vision_position_estimate"
    track_width_m: float = 0.0  # WHEEL_DISTANCE needs it (> 0) to give a yaw rate; 0 = forward speed only
    wheel_left: int = 0  # WHEEL_DISTANCE indices (WENC_POS_Y < 0 is the left wheel)
    wheel_right: int = 1
    yaw_rate_source: str = "attitude"  # "attitude" (gyro) or "wheels"
    steering_channel: int = 1  # RCMAP defaults for Rover
    throttle_channel: int = 3
    link_timeout_s: float = 3.0
    heartbeat_hz: float = 1.0
    timesync_hz: float = 1.0
    timesync_reply_hz: float = 20.0  # at most this many TIMESYNC replies a second (PX4 asks at up to 10 Hz)
    # ATTITUDE's roll and pitch (the autopilot's gravity-referenced AHRS) go with each odometry
    # sample as the direction of gravity, with this σ; 0: not used
    gravity_sigma_deg: float = 2.0
    bind: str = ""  # udp mode=out: local address ("" = the one that routes to the target)
    request_rates: bool = True
    rates_hz: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES_HZ))
    origin: tuple[float, float, float] | None = None  # (lat_deg, lon_deg, alt_m)
    signing_key: str | None = None  # path of a 32-byte key file, mode 0600
    allow_unsigned: bool = False
    # smallest variances in pose_covariance: only keep zeros out (ArduPilot PR 8730); 1 mm and
    # 0.06°, far below the autopilots' own floors (VISO_*_M_NSE, EKF2_EV*_NOISE: docs/mavlink.md §8)
    floor_pos_m2: float = 1e-6
    floor_ang_rad2: float = 1e-6
    queue_size: int = 512
    # when the autopilot reports its vision yaw off its own heading before arming ("VisOdom: yaw
    # diff") and the vehicle stands still: ask it to align them (aux function 80), at most every
    # ALIGN_INTERVAL_S (docs/mavlink.md §6)
    align_yaw: bool = True
