"""MAVLink output of the VIO estimate to ArduPilot and PX4 (VISION_POSITION_ESTIMATE, VISION_SPEED_ESTIMATE,
ODOMETRY), with our HEARTBEAT, TIMESYNC answers, link health, reconnection and an optional EKF origin.

Why the shape: the estimator must never wait on a serial port, so `send_state()` only keeps the newest
state; the actual sending happens in `poll()` (called by our own thread after `start()`, or inline from
`send_state()` when no thread runs) on a fixed schedule at `rate_hz`, always with the newest state and
never twice the same one. Link problems (unplugged serial, refused socket) close the connection and
reopen it with a back-off; each transition is logged once, not each failed write.

Time stamps: `time_usec` is the state's own time (NavState.t_ns, host CLOCK_MONOTONIC) / 1000, and our
TIMESYNC answers use the same clock, so PX4 can map our stamps onto its clock; ArduPilot estimates the
offset from the stamps themselves (its VISO_DELAY_MS covers the remaining latency).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import secrets
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.mavlink_frames import (
    R_NED_WORLD,
    SNAP_DEG,
    VehicleOdometry,
    mount_rotation,
    mount_rpy_deg_from_matrix,
    mount_transform,
    to_vehicle_odometry,
    upper_triangle,
)
from drivers.mavlink_link import (  # noqa: F401 (mavutil, open_connection re-exported)
    OUR_COMPONENT,
    RECONNECT_MAX_S,
    RECONNECT_MIN_S,
    UNPACKABLE,
    MavlinkLink,
    check_url,
    is_autopilot_heartbeat,
    mavlink,
    mavutil,
    open_connection,
    unpackable,
)
from vio import VioError
from vio.config import MavlinkConfig
from vio.geometry import make_T, rot_to_quat_wxyz
from vio.io.atomic import replace_atomically
from vio.types import NavState

log = logging.getLogger(__name__)

SUPPORTED_MESSAGES = ("VISION_POSITION_ESTIMATE", "VISION_SPEED_ESTIMATE", "ODOMETRY")
HEARTBEAT_PERIOD_NS = 1_000_000_000
FLAP_CHANGES, FLAP_WINDOW_NS = 4, 3_000_000_000  # tracking changes within the window that count as flapping
# SET_GPS_GLOBAL_ORIGIN / SET_HOME_POSITION after each link-up, 1 s apart, until the autopilot reports
# GPS_GLOBAL_ORIGIN (an autopilot still booting drops them: without an origin GUIDED take-off is refused),
# at most ORIGIN_MAX_SENDS times; then one warning.
ORIGIN_MAX_SENDS = 60
# Once confirmed, while the autopilot is disarmed, GPS_GLOBAL_ORIGIN is asked for every ORIGIN_RECHECK_NS; no answer
# within ORIGIN_ANSWER_NS (an autopilot without an origin sends none) means it lost the origin, which is set again.
# Why: ArduPilot confirms an origin set while it boots, then its EKF3 initialises and drops it (NavEKF3::
# InitialiseFilter clears the shared origin): ArduCopter SITL then had no origin and no home (1 of 6 flights).
ORIGIN_RECHECK_NS, ORIGIN_ANSWER_NS = 5_000_000_000, 3_000_000_000
# A start in flight continues in the autopilot's frame: its own estimate (LOCAL_POSITION_NED, ATTITUDE), asked for at
# this rate when it is heard armed before our first pose, is taken only when this fresh at our first tracked pose.
AP_POSE_RATE_HZ = 10.0
AP_POSE_MAX_AGE_NS = 500_000_000
# what the output reads from a link it shares with the MAVLink IMU (the link's reader hands these over)
LINK_MESSAGES = frozenset({"HEARTBEAT", "TIMESYNC", "GPS_GLOBAL_ORIGIN", "COMMAND_ACK", "LOCAL_POSITION_NED",
                           "ATTITUDE"})
# land_after_loss_s: MAV_CMD_NAV_LAND is repeated 1 s apart until the autopilot accepts it (COMMAND_ACK) or
# is seen disarmed, at most LAND_MAX_SENDS times per loss (a dropped command must not leave it dead-reckoning).
LAND_MAX_SENDS = 5
# No estimate at all for this long (camera and IMU silent together: an OAK shares one cable for both; or the
# estimator stopped) is a loss of tracking like a dark camera: the same STATUSTEXT, and land_after_loss_s counts
# from the last estimate. The estimator sends IMU-rate states, the daemon at least frame-rate ones.
NO_ESTIMATE_LOST_NS = 500_000_000
# A vehicle this far from level at its first pose most likely stands level with a wrong [mavlink] mount (a
# camera-down rig set up as camera-forward is 90 deg off); a copter in flight rarely leans this far.
MOUNT_TILT_WARN_DEG = 45.0
MOUNT_TILT_NOTE_DEG = 10.0  # from here the first pose's lean is said in the log (no STATUSTEXT)

@dataclass
class MavlinkStats:
    """Counters for `vio status` and tests; `sent` is per message name."""

    states_in: int = 0
    states_sent: int = 0
    states_superseded: int = 0  # replaced by a newer state before their send slot
    states_not_tracking: int = 0
    states_not_finite: int = 0  # a NaN or infinite pose, velocity or covariance: sent as a loss of tracking
    states_too_old: int = 0  # older than max_state_age_ms: not sent, a loss of tracking (not also withheld: below)
    # not sent while the daemon withheld every pose (withhold(): the IMU clock unsure), tracking or not: the daemon's
    # gate hands them on as lost already, so only counting every one gives the count of states it held back
    states_withheld: int = 0
    withheld_for: str = ""  # why the last withholding spell held them back (kept after it ends; "" before any)
    states_refused_armed: int = 0  # a replay's poses withheld while the autopilot said it was armed (poses_to_armed)
    states_refused_unheard: int = 0  # a replay's poses withheld while no autopilot heartbeat said it was disarmed
    # reached its send slot with no connection (our own one being reopened, a shared link reconnecting): dropped there
    states_link_closed: int = 0
    sent: dict = field(default_factory=dict)
    autopilot_heartbeats: int = 0
    other_heartbeats: int = 0  # ours echoed back, a GCS's, a peripheral's, another vehicle's: not trusted
    origin_confirmed: bool = False  # the autopilot reported GPS_GLOBAL_ORIGIN after we set it
    # ... and whether that origin is [mavlink] origin_* (None before an answer): an armed autopilot's own origin is
    # kept, and confirmed said nothing of whose it was (review2's note)
    origin_ours: bool | None = None
    origin_lost: int = 0  # times a confirmed origin went unreported (the autopilot dropped it) and was set again
    land_requests: int = 0  # MAV_CMD_NAV_LAND sent because tracking was lost land_after_loss_s (all losses)
    land_accepted: bool = False  # the autopilot acknowledged the last loss's LAND request
    timesync_answered: int = 0
    link_losses: int = 0
    autopilot_restarts: int = 0  # seen in its HEARTBEAT (booting again) or its TIMESYNC clock (gone back)
    reconnects: int = 0
    io_errors: int = 0
    last_latency_ms: float = float("nan")  # send time - state time (meaningful when t_ns is host time)
    first_tilt_deg: float = float("nan")  # vehicle tilt from level at the first pose sent (mount check)


# An autopilot that reboots faster than link_timeout_s (ArduCopter SITL: 2.3 s of silent heartbeats; a flight
# controller's watchdog recovery in flight) keeps the link up but forgets the EKF origin. It shows in its HEARTBEAT
# (system_status back to BOOT after it had been running; not UNINIT, which PX4 sends for states it does not map,
# such as a failed preflight check) and in its own TIMESYNC requests (component 1: ts1 is its time since boot;
# ArduPilot asks every 10 s, PX4 more often; a companion program's requests on the same system carry wall time).
BOOTING_STATES = (mavlink.MAV_STATE_BOOT,)
RESTART_CLOCK_BACK_NS = 500_000_000  # a TIMESYNC ts1 this far behind the last one: its clock restarted

ANOTHER_CLOCK_NS = 2_000_000_000  # pose stamps this far ahead of the host clock are on another clock
MAX_LEVER_ARM_M = 2.0  # [mavlink] mount_offset_m: no drone's IMU sits further from its centre


# The pose messages' fields are float32 (at most 3.4e38): a larger finite number failed to pack, and the pose was
# dropped as a send error while the status said running (a review's note); the frame conversion multiplies a little.
MAX_SENDABLE = 1e30


NOT_FINITE_TEXT = ("the estimate holds a NaN or infinite value (or one beyond 1e30), or a negative variance (pose, "
                   "velocity or covariance)")
TIME_USEC_END = 2 ** 64  # the pose messages' time_usec is unsigned 64-bit


def _unsendable(state: NavState) -> tuple[str, str] | None:
    """Why the pose messages cannot carry `state`: (kind, the why in words), or None when they can. Every number
    must be finite and within float32's range, every variance >= 0, and the stamp within time_usec's unsigned range
    (a negative one failed to pack and was dropped as a send error, the status saying nothing: a review's note)."""
    if not (all(bool((np.abs(a) < MAX_SENDABLE).all()) for a in (state.T_world_body, state.v_world, state.omega_body,
                                                                  state.cov_pose, state.cov_vel))
            and bool((np.diag(state.cov_pose) >= 0).all() and (np.diag(state.cov_vel) >= 0).all())):
        return "values", NOT_FINITE_TEXT
    if not 0 <= int(state.t_ns) // 1000 < TIME_USEC_END:
        return "stamp", (f"its time stamp t_ns = {int(state.t_ns)} is outside the messages' unsigned time_usec (0 "
                         "to 2^64 us; a stamp before the clock's zero)")
    return None


@dataclass(frozen=True)
class Continuity:
    """What an output reopened after a failure goes on from (MavlinkOutput.continuity / continue_from): the closed
    one's reset_counter, tracking state and loss clock (clock times on the output's clock: one factory makes both),
    and the autopilot's estimate it read for a start in flight's frame. A reopened output began afresh: a loss went on
    with no clock of its own (no LAND, no 'tracking lost' for one begun while none was open), and a random first
    counter could repeat the last one sent at a step (review notes)."""

    reset_offset: int
    last_reset_counter: int | None
    last_loop_jumps: int
    counter_sent: int | None
    tracked_frame: tuple[int, int] | None
    last_sent_t_ns: int | None
    tracking: bool | None
    lost_since_ns: int | None
    land_done: bool
    land_left: int
    land_accepted: bool
    ap_local: tuple[int, np.ndarray, np.ndarray] | None
    ap_yaw: tuple[int, float, float] | None
    first_tilt_deg: float


def check_mavlink_config(cfg: MavlinkConfig) -> None:
    """What the output could never send with (VioError naming the key): checked when `vio run` / `vio config check`
    start, not found by the output thread, which would retry it forever."""
    if cfg.url:
        check_url(cfg.url)
    bad = [m for m in cfg.messages if m not in SUPPORTED_MESSAGES]
    if bad or not cfg.messages:
        raise VioError(f"[mavlink] messages: unknown {bad or 'none given'}; supported: {list(SUPPORTED_MESSAGES)}")
    twice = sorted({m for m in cfg.messages if list(cfg.messages).count(m) > 1})
    if twice:  # every state went out twice, and the autopilot fused each one twice (a QA sweep)
        raise VioError(f"[mavlink] messages = {list(cfg.messages)}: {', '.join(twice)} named twice")
    for key in ("mount_rpy_deg", "mount_offset_m"):
        v = getattr(cfg, key)
        if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
            raise VioError(f"[mavlink] {key} must be 3 finite numbers, got {v!r}")
    if max(abs(float(x)) for x in cfg.mount_offset_m) > MAX_LEVER_ARM_M:
        raise VioError(f"[mavlink] mount_offset_m = {list(cfg.mount_offset_m)}: a lever arm over {MAX_LEVER_ARM_M} m "
                       "(the IMU's position from the vehicle's centre, in metres; centimetres would swing every "
                       "position sent by metres at each turn)")
    lat, lon = cfg.origin_lat_deg, cfg.origin_lon_deg
    if math.isfinite(lat) != math.isfinite(lon) or \
            (math.isfinite(lat) and not (-90 <= lat <= 90 and -180 <= lon <= 180)):
        raise VioError(f"[mavlink] origin_lat_deg / origin_lon_deg = {lat}, {lon}: degrees, latitude within +-90 and "
                       "longitude within +-180, both or neither (a ground station's 1e7 integers divided by 1e7)")
    if not math.isfinite(cfg.origin_alt_m) or abs(cfg.origin_alt_m) > 10_000:
        raise VioError(f"[mavlink] origin_alt_m = {cfg.origin_alt_m}: metres above mean sea level, within +-10 km")
    both = {"VISION_POSITION_ESTIMATE", "VISION_SPEED_ESTIMATE"} & set(cfg.messages)
    if "ODOMETRY" in cfg.messages and both:
        raise VioError(f"[mavlink] messages = {list(cfg.messages)}: ODOMETRY and {sorted(both)} carry the same "
                       "estimate, which ArduPilot would fuse twice; send ODOMETRY alone (PX4, ArduPilot) or the "
                       "VISION_* ones")
    # Only ODOMETRY has a quality field the autopilots check (VISO_QUAL_MIN, EKF2_EV_QMIN); VISION_* would
    # carry the lost pose as a good one.
    if cfg.lost_output in ("quality0", "failed") and list(cfg.messages) != ["ODOMETRY"]:
        raise VioError(f"[mavlink] lost_output = {cfg.lost_output!r} needs messages = ['ODOMETRY'] (VISION_* "
                       "messages have no quality field, so a lost pose would look valid)")


class MavlinkOutput:
    """Sends NavStates to an autopilot over MAVLink 2 as component 197 (visual-inertial odometry).

    Use `send_state()` (or call the object: it is a NavState sink), optionally `start()` a background
    thread for exact-rate sending and prompt TIMESYNC answers, and `close()` at the end.
    `clock_ns` is injectable so that scheduling is testable without real time. With `link` (a
    drivers.mavlink_link.MavlinkLink, e.g. the one the MAVLink IMU source reads) the output opens no
    connection of its own: it sends through the link and gets HEARTBEAT/TIMESYNC from its reader thread.
    """

    def __init__(self, cfg: MavlinkConfig, url: str | None = None,
                 clock_ns: Callable[[], int] = time.monotonic_ns, T_body_cam0: np.ndarray | None = None,
                 link: MavlinkLink | None = None, counter_file: str | None = None,
                 max_state_age_ms: float | None = None, random_first_counter: bool = False,
                 poses_to_armed: bool = True) -> None:
        self.cfg = cfg
        # False for `vio replay --mavlink` and `vio run` with a recorded or simulated source: their poses are another
        # flight's, never this vehicle's; an armed autopilot (a vehicle that may fly, or flies) would fly on them, so
        # none goes out while it says armed
        self._poses_to_armed = poses_to_armed
        self._armed_refusal_said = False
        self._unheard_refusal_said = False
        self._refusing: str | None = None  # the last pose of a replay was withheld: "armed" / "unheard"
        self._link = link
        self.url = link.url if link is not None else url if url is not None else cfg.url
        if not self.url:
            raise VioError("[mavlink] url is empty: give a connection string such as udpout:127.0.0.1:14550")
        check_mavlink_config(cfg)
        if link is None and url is not None:
            check_url(url, "MAVLink connection")
        self._lost_as_quality0 = cfg.lost_output in ("quality0", "failed")
        # ODOMETRY quality while lost: -1 is "failed" in the MAVLink spec, rejected by ArduPilot's VISO_QUAL_MIN at
        # its default 0 (PX4 fuses any quality unless EKF2_EV_QMIN >= 1); 0 is "unknown", fused by both at 0
        self._lost_quality = -1 if cfg.lost_output == "failed" else 0
        # A start in flight (armed before our first pose): the first tracked pose is placed where the autopilot's own
        # estimate has the vehicle, and every pose after it goes through the same yaw turn and shift (NED). EKF3
        # resets its position to the external nav's at a reset_counter change; a new process's world starts where
        # the vehicle was, so its position moved by all the vehicle had flown (1.3 m on the SITL, docs/autopilot.md).
        self._continue_frame = False
        # (arrival ns, LOCAL_POSITION_NED x, y, z, its vx, vy, vz): carried to our first pose's stamp at its velocity
        self._ap_local: tuple[int, np.ndarray, np.ndarray] | None = None
        self._ap_yaw: tuple[int, float, float] | None = None  # (arrival ns, ATTITUDE yaw [rad], its rate [rad/s])
        self._align: tuple[np.ndarray, np.ndarray, float] | None = None  # (R about down, shift [m], yaw [rad])
        self._px4_said = False  # the PX4 EKF2_EV_QMIN advice, once
        self._frame_kept = False  # the frame is the one of the output this one replaced (keep_autopilot_frame)
        if cfg.lost_output == "quality0":
            log.warning("[mavlink] lost_output = 'quality0': a lost pose goes out with quality 0 ('unknown'), which "
                        "ArduPilot (VISO_QUAL_MIN) and PX4 (EKF2_EV_QMIN) fuse at their default 0; 'failed' sends "
                        "-1, which ArduPilot rejects at its default (PX4 needs EKF2_EV_QMIN = 1 for either)")
        # None until the mount is known (mount = camera-*: from the calibration, see set_camera_mount)
        self.T_frd_body: np.ndarray | None = None
        if cfg.mount == "rpy":
            self.T_frd_body = mount_transform(cfg.mount_rpy_deg, cfg.mount_offset_m)
        elif T_body_cam0 is not None:
            self.set_camera_mount(T_body_cam0)
        self._mount_warned = False
        self._unsendable_said: set[str] = set()  # the error line of each kind of unsendable state, said once
        self._unsendable_why: str | None = None  # why the newest state cannot be sent (health(); None: it can)
        # the newest state was not finite: nothing goes out until a whole one comes (health(): `vio status` said
        # running at quality 100 meanwhile, a review's finding)
        self._not_finite_spell = False
        self._clock = clock_ns
        self._period_ns = int(round(1e9 / cfg.rate_hz))
        self._timeout_ns = int(cfg.link_timeout_s * 1e9)
        self.stats = MavlinkStats()
        self.target_system = cfg.target_system
        self.system_id = cfg.system_id or cfg.target_system

        self._conn: Any = None
        self._reopen_at_ns = 0
        self._backoff_s = RECONNECT_MIN_S
        self._conn_failed_logged = False
        self._pending: NavState | None = None
        self._pending_at_ns = 0  # clock time the pending state was taken (a closed link drops it a period later)
        self._last_sent_t_ns: int | None = None
        self._next_send_ns = 0
        self._next_heartbeat_ns = 0
        self._last_ap_heartbeat_ns: int | None = None
        self._link_up = False
        self._origin_left = 0
        self._next_origin_ns = 0
        # its tries were spent only asking an armed autopilot (unconfirmed): set once it is heard disarmed
        self._origin_owed = False
        self._origin_recheck_ns: int | None = None  # when to ask for the confirmed origin again (None: not checking)
        self._origin_asked_ns: int | None = None  # when the unanswered request went out
        self._unpackable_said: set[str] = set()  # message types that could not be packed (said once each)
        # states older than this (t_ns on the host clock, as `vio run` and `vio replay --mavlink` stamp them) are
        # not sent: None or 0 = no limit (states stamped on another clock: tests, tools)
        self._max_age_ns = int(max_state_age_ms * 1e6) if max_state_age_ms else None
        self._too_old_spell = False
        self._withheld_for: str | None = None  # why the daemon holds every pose back (withhold()); None: it does not
        self._counter_file = Path(counter_file) if counter_file else None
        self._random_first_counter = random_first_counter  # `vio run` with no counter_file; a replay starts at 0
        self._counter_saved: int | None = None
        # added to the estimator's reset_counter: where this process starts (`counter_file`), and resets forced here
        self._reset_offset = self._first_counter()
        self._last_reset_counter: int | None = None
        self._counter_sent: int | None = None  # the reset_counter of the newest pose sent (health(): `vio status`)
        # (estimator reset_counter, this process's offset) of the newest tracked state: a lost pose goes out as
        # lost_output's -1/0 only in a frame that was once tracked (an estimator started from the IMU alone, its
        # cameras black from boot, sent its prior's 1 mm covariance with quality -1: a QA sweep)
        self._tracked_frame: tuple[int, int] | None = None
        self._last_loop_jumps = 0
        self._tracking: bool | None = None
        self._lost_since_ns: int | None = None  # clock time tracking was lost (None while tracking)
        self._last_state_at_ns: int | None = None  # clock time the newest state arrived (send_state)
        self._land_left = 0  # LAND requests still to send for the current loss
        self._land_done = False  # this loss has had its LAND request (one per loss)
        self._next_land_ns = 0
        self._ap_armed = False  # from the autopilot's HEARTBEAT base_mode
        self._ap_running = False  # its HEARTBEAT has shown it past booting (restart detection)
        self._ap_ts1: int | None = None  # its last TIMESYNC request's ts1 [ns since its boot]
        self._changes: list[int] = []  # clock times of recent tracking changes (flap detection)
        self._flapping = False
        self._lock = threading.RLock()  # guards the connection and the schedule
        self._pending_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._inbox: deque = deque(maxlen=1000)  # link mode: HEARTBEAT/TIMESYNC handed over by the link's reader
        if link is None:
            self._open()  # raises VioError for a malformed url; a missing device is retried later
        self._wake_r, self._wake_w = os.pipe()  # lets send_state()/close() interrupt the thread's select()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        if link is not None:
            link.subscribe(LINK_MESSAGES, self._on_link_message)
            link.acquire()

    # ---------------------------------------------------------------- public API

    def set_camera_mount(self, T_body_cam0: np.ndarray) -> None:
        """Derive the IMU mounting from the calibration (mount = camera-forward / camera-down); no pose is
        sent before the mount is known. Raises VioError when the calibration does not decide it."""
        m = mount_rotation(self.cfg.mount, self.cfg.mount_rpy_deg, np.asarray(T_body_cam0, dtype=float)[:3, :3],
                           self.cfg.camera_tilt_deg)
        T = make_T(m.R_frd_body, np.asarray(self.cfg.mount_offset_m, dtype=float))
        if self.T_frd_body is not None and np.allclose(T, self.T_frd_body):
            return  # the daemon hands the mount over again once the output is up: said once is enough
        self.T_frd_body = T
        rpy = np.round(mount_rpy_deg_from_matrix(m.R_frd_body), 1).tolist()
        log.info("IMU mount from the calibration (%s): roll/pitch/yaw %s deg in the vehicle FRD frame", m.note, rpy)
        if m.off_axis_deg > SNAP_DEG:
            log.warning("the IMU is %.1f deg from the airframe's axes: right for an IMU inside a tilted camera (OAK); "
                        "if your IMU is square to the frame, the camera is tilted by that much: set [mavlink] "
                        "camera_tilt_deg. Check the attitude on the bench (docs/first-flight.md)", m.off_axis_deg)

    @property
    def states_sent(self) -> int:
        """Pose states that went out on the link."""
        return self.stats.states_sent

    @property
    def link_up(self) -> bool:
        """True while the autopilot's heartbeats arrive (within link_timeout_s)."""
        return self._link_up

    @property
    def connected(self) -> bool:
        return self._link.connected if self._link is not None else self._conn is not None

    def counters(self) -> dict[str, int]:
        """The counts of MavlinkStats (every int field): what the daemon adds up over the outputs it reopens, so that
        `vio status` counts the whole run (a reopened output starts its own at 0)."""
        return {f.name: v for f in dataclasses.fields(self.stats) if type(v := getattr(self.stats, f.name)) is int}

    def health(self) -> dict:
        """Flat snapshot for the status file: link, ids, the state of the refusals and the counters."""
        st = self.stats
        return {"link_up": self._link_up, "connected": self.connected, "url": self.url,
                "system_id": self.system_id, "target_system": self.target_system,
                "withholding_old_poses": self._too_old_spell, "withholding_for": self._withheld_for,
                "withholding_not_finite": self._not_finite_spell, "withholding_not_sendable": self._unsendable_why,
                "withheld_for": st.withheld_for,
                "poses_to_armed": self._poses_to_armed, "withholding_replay_poses": self._refusing,
                "last_latency_ms": st.last_latency_ms, "land_after_loss_s": self.cfg.land_after_loss_s,
                "land_accepted": st.land_accepted, "origin_confirmed": st.origin_confirmed,
                "origin_ours": st.origin_ours,
                "first_tilt_deg": st.first_tilt_deg, **self.counters(),
                **({} if self._counter_sent is None else {"reset_counter": self._counter_sent})}

    def send_state(self, state: NavState) -> bool:
        """Offer the newest estimate; it is sent in the next slot of the `rate_hz` schedule, or never
        if a newer one arrives first. A state with tracking=False cancels the pending one (nothing stale
        goes out) and sends nothing. Returns whether the state was taken for sending."""
        taken = False
        # read once: the daemon says withhold() before each state, from the thread that calls this
        withheld = self._withheld_for is not None
        too_old = False  # this state: older than max_state_age_ms (its one reason, unless withheld)
        if self._max_age_ns is not None:
            age = self._clock() - state.t_ns
            if age < -ANOTHER_CLOCK_NS and self.stats.states_in == 0:
                # the first pose stamped ahead of the host clock by seconds: not on it (a recording's own stamps,
                # replayed as fast as it goes), so an age says nothing; said once, and the check is off for this
                # output (decided on the first pose only: one bad stamp later must not switch a safety gate off)
                log.warning("pose stamps are %.1f s ahead of this host's clock: not on it; [mavlink] "
                            "max_state_age_ms cannot be checked and is off", -age / 1e9)
                self._max_age_ns = None
                self._too_old_spell = False
            elif age > self._max_age_ns:
                # flown on as if it were now: never. The estimator is behind its sensors (CPU) or the process was
                # stalled; poses 0.5-2.9 s old went out at quality 100 (a review's finding). One reason a state: one
                # that is withheld too counts as withheld only, the reason that stopped it first (the daemon's gate
                # held it back before it reached this output: it says withhold() before each state, and its
                # StampErrorGate handed the state on as lost already); states_withheld stays every state of a spell
                too_old = True
                self.stats.states_too_old += not withheld
                if not self._too_old_spell:
                    log.warning("poses %.0f ms old are not sent (beyond [mavlink] max_state_age_ms = %.0f): the "
                                "estimator is behind its sensors (CPU load?) or was stalled; a loss of tracking "
                                "until they are fresh", age / 1e6, self._max_age_ns / 1e6)
                self._too_old_spell = True
                state = dataclasses.replace(state, tracking=False, quality=0)
            elif self._too_old_spell:  # a fresh state, tracking or not, ends the spell
                self._too_old_spell = False
                log.info("poses fresh again (%.0f ms old)", age / 1e6)
        if withheld:
            self.stats.states_withheld += 1
            if state.tracking:
                state = dataclasses.replace(state, tracking=False, quality=0)
        unsendable = _unsendable(state)
        finite = unsendable is None
        self._not_finite_spell, self._unsendable_why = not finite, None if unsendable is None else unsendable[1]
        if unsendable is not None:
            # never sent, not even as a lost pose: the autopilot would read a NaN covariance as anything
            if unsendable[0] not in self._unsendable_said:
                log.error("no pose sent: %s; a loss of tracking until it is whole again", unsendable[1])
                self._unsendable_said.add(unsendable[0])
            # one reason a state: a withheld or too old one is counted there (it stopped the state first)
            self.stats.states_not_finite += not (withheld or too_old)
            state = dataclasses.replace(state, tracking=False, quality=0)
        with self._pending_lock:
            self.stats.states_in += 1
            self._last_state_at_ns = self._clock()
            changed = self._tracking is not None and state.tracking != self._tracking
            self._tracking = state.tracking
            if changed:
                self._lost_since_ns = None if state.tracking else self._clock()
                self._land_done = self._land_done and not state.tracking
                if state.tracking:
                    self._land_left = 0
            if state.tracking and finite:
                self._tracked_frame = (state.reset_counter, self._reset_offset)
            never_tracked = self._tracked_frame != (state.reset_counter, self._reset_offset)
            if self.T_frd_body is None:
                self._pending = None
                if not self._mount_warned:
                    log.warning("no pose sent: the IMU mount is not known yet (mount = %r needs the calibration)",
                                self.cfg.mount)
                    self._mount_warned = True
            elif not state.tracking and (not self._lost_as_quality0 or not finite or self._too_old_spell
                                         or withheld or never_tracked):
                # one reason a state: the withholding's, the age's or the NaN's above (a tracked state too old or
                # not finite counted as 'not tracking' too: 4 states in, 1 sent, 5 reasons)
                self.stats.states_not_tracking += not (withheld or too_old or not finite)
                self._pending = None
            elif (self._last_sent_t_ns is not None and state.t_ns <= self._last_sent_t_ns) or \
                    (self._pending is not None and state.t_ns < self._pending.t_ns):
                pass  # not newer than what the autopilot already has, or than the state waiting for its slot
            else:
                if self._pending is not None:
                    # waited a whole period with no connection: the closed link stopped it, not the rate limit
                    if not self.connected and self._clock() - self._pending_at_ns >= self._period_ns:
                        self.stats.states_link_closed += 1
                    else:
                        self.stats.states_superseded += 1
                self._pending, self._pending_at_ns = state, self._clock()
                taken = True
        if changed:
            self._on_tracking_change(state.tracking)
        if self._thread is None:
            self.poll()
        else:
            self._wake()
        return taken

    __call__ = send_state  # NavStateSink: sink(state)

    def withhold(self, why: str | None) -> None:
        """While `why` is set no pose goes out at all, not even lost_output's -1/0 ones (a loss of tracking, as for
        poses too old); the first of a spell says `why` (at most 50 characters) to the ground station as a
        STATUSTEXT. The daemon sets it while the IMU source's stamps are too uncertain to fly on (its output stage's
        StampErrorGate, [mavlink] max_stamp_error_ms), and calls this before every state (so a reopened output
        learns it at once); None ends it."""
        with self._pending_lock:
            was, self._withheld_for = self._withheld_for, why
            if why is not None:
                self._pending = None  # a pose taken before the spell does not go out in it
                self.stats.withheld_for = why
        if why is not None and was is None:
            with self._lock:
                if self.connected and self._replay_refusal() != "armed":
                    self._statustext(mavlink.MAV_SEVERITY_WARNING, why)

    def autopilot_frame(self) -> tuple[tuple[np.ndarray, np.ndarray, float] | None, bool] | None:
        """Where this output's poses go: (the turn and shift into the autopilot's frame chosen at a start in flight,
        None for the estimator's own frame; whether that choice is still to come), or None while no autopilot was
        heard (nothing chosen yet). The daemon hands it to the output it reopens after a failure. Read without the
        lock: the output failed, and its thread may be stuck holding it."""
        if self._last_ap_heartbeat_ns is None and not self._frame_kept:
            return None
        return self._align, self._continue_frame

    def frame_pending(self) -> bool:
        """Is the frame of a start in flight still to be chosen (at the first tracked pose sent)? world_frame_turn()
        says None until then, though a turn may come."""
        return self._continue_frame

    def world_frame_turn(self) -> np.ndarray | None:
        """The turn and shift of a start in flight as a transform of the estimator's world (z up, world' = T @ world),
        or None (poses go in the estimator's own frame). The loop output takes it out of a pose it maps into a map's
        frame, which is the autopilot's already (vio.loop.output.CorrectedOutput.frame_turn)."""
        align = self._align
        if align is None:
            return None
        R, shift, _ = align
        return make_T(R_NED_WORLD @ R @ R_NED_WORLD, R_NED_WORLD @ shift)

    def keep_autopilot_frame(self, frame: tuple[tuple[np.ndarray, np.ndarray, float] | None, bool] | None) -> None:
        """Send in the frame of the output this one replaces (its autopilot_frame()): the start in flight was the
        process's, not this output's. A reopened output sent in the estimator's own frame when a tracked pose came
        before the autopilot's next heartbeat, at its new reset_counter: EKF3 resets to the external nav's position
        there, and the autopilot's position jumped by all the vehicle had flown before the start (a review's)."""
        if frame is None:
            return
        with self._lock:
            self._align, self._continue_frame = frame
            self._frame_kept = True

    def continuity(self) -> Continuity:
        """What the output reopened after this one goes on from (the daemon hands it over). Read without the lock:
        this output failed, and its thread may be stuck holding it."""
        return Continuity(self._reset_offset, self._last_reset_counter, self._last_loop_jumps, self._counter_sent,
                          self._tracked_frame, self._last_sent_t_ns, self._tracking, self._lost_since_ns,
                          self._land_done, self._land_left, self.stats.land_accepted,
                          self._ap_local, self._ap_yaw, self.stats.first_tilt_deg)

    def continue_from(self, c: Continuity | None) -> None:
        """Go on from the output this one replaces (its continuity()), before any state: its reset_counter (moved only
        by the estimator from here), its tracking state and loss clock (a loss goes on, with its LAND; one that begins
        now is a change), its reading of the autopilot's estimate, its mount check."""
        if c is None:
            return
        with self._lock, self._pending_lock:
            self._reset_offset, self._last_reset_counter, self._last_loop_jumps = (c.reset_offset, c.last_reset_counter,
                                                                                   c.last_loop_jumps)
            self._counter_sent, self._tracked_frame, self._last_sent_t_ns = (c.counter_sent, c.tracked_frame,
                                                                             c.last_sent_t_ns)
            self._tracking, self._lost_since_ns = c.tracking, c.lost_since_ns
            # no estimate from here for NO_ESTIMATE_LOST_NS is a loss (the closed one's last arrival would make the
            # states that came while none was open, dropped by the daemon, look like silence)
            self._last_state_at_ns = self._clock()
            self._land_done, self._land_left, self.stats.land_accepted = c.land_done, c.land_left, c.land_accepted
            self._next_land_ns = 0
            self.stats.first_tilt_deg = c.first_tilt_deg
            if not self._frame_kept and c.counter_sent is not None:
                # the closed one sent poses in the process's own frame (it never heard the autopilot): a start in
                # flight this one's thread took the autopilot's first heartbeat (armed) for before the hand-over
                # would turn the next pose into the autopilot's frame at the same reset_counter, a step fused as a
                # measurement
                if self._continue_frame:
                    self._ask_ap_pose(0)  # its estimate's rate back to the autopilot's default
                self._continue_frame, self._align = False, None
            # the newer reading of the autopilot's estimate (this one's thread may have read one already)
            self._ap_local = max((r for r in (self._ap_local, c.ap_local) if r is not None), key=lambda r: r[0],
                                 default=None)
            self._ap_yaw = max((r for r in (self._ap_yaw, c.ap_yaw) if r is not None), key=lambda r: r[0],
                               default=None)
        log.info("reopened output goes on from the one before it: reset_counter offset %d, %s", c.reset_offset,
                 "tracking" if c.tracking else "no tracking state yet" if c.tracking is None else "tracking lost")

    def force_reset(self) -> None:
        """Bump reset_counter without an estimator reset (e.g. the estimator was re-created and its own
        counter restarted), so the autopilot drops its old reference."""
        with self._pending_lock:
            self._reset_offset += 1

    def start(self) -> MavlinkOutput:
        """Run `poll()` in a daemon thread on the send/heartbeat schedule (at least every 10 ms)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="mavlink-out", daemon=True)
            self._thread.start()
        return self

    def close(self, final: bool = True) -> None:
        """Stop the thread and close the connection; safe to call twice. With `final` (not a reconnect) a link
        that is up hears it first: the poses stop because VIO stopped, not because vision failed."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            if final and self._link_up and (self._link is not None or self._conn is not None):
                with contextlib.suppress(Exception):
                    self._statustext(mavlink.MAV_SEVERITY_WARNING, "VIO stopped: no more poses")
            if self._link is not None:
                self._link.unsubscribe(self._on_link_message)
                self._link.release()
                self._link = None
            self._close_conn()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # pipe full (already woken) or closed
            os.write(self._wake_w, b"w")

    def __enter__(self) -> MavlinkOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def poll(self) -> None:
        """Do what is due now: reconnect, read the autopilot (HEARTBEAT, TIMESYNC), link health, our
        heartbeat, origin messages, and the pose messages of the newest state."""
        with self._lock:
            now = self._clock()
            if self._link is not None:
                closed = not self._link.connected
            else:  # (re)open our own connection when due
                closed = self._conn is None and (now < self._reopen_at_ns or not self._open())
            if closed:
                # no connection (a serial port gone): no heartbeat either, so the link goes down after
                # link_timeout_s. It stayed 'up' (status healthy) for as long as the port was gone (a walk-through)
                self._update_link(now)
                # a state that waited a whole period past its slot with no connection is dropped and counted (it was
                # kept and then counted superseded, or sent stale on reopening); one that came in the gap of a link
                # that reconnects at once (a shared link's reader reopens it within ms) stays for the link's return
                # (dropped at once, it went nowhere: the poses came a state period apart twice, a review's finding).
                # One reason a state: nothing else (its age, a replay's refusal) is checked with no connection
                with self._pending_lock:
                    if (self._pending is not None and now >= self._next_send_ns
                            and now - self._pending_at_ns >= self._period_ns):
                        self._pending = None
                        self.stats.states_link_closed += 1
                return
            self._read_incoming(now)
            self._update_link(now)
            self._check_flapping(now)
            self._check_estimates_stopped(now)
            self._check_land_after_loss(now)
            if now >= self._next_heartbeat_ns:
                self._next_heartbeat_ns = _next_slot(self._next_heartbeat_ns, HEARTBEAT_PERIOD_NS, now)
                self._send(mavlink.MAVLink_heartbeat_message(
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                    mavlink.MAV_STATE_ACTIVE, 3), "HEARTBEAT")
            # a replay sets no EKF origin on an armed autopilot either (the review: its origin_lat/lon went out to it),
            # nor on one silent past link_timeout_s, which may have armed since (its 60 tries went on through a loss)
            if self._origin_left > 0 and now >= self._next_origin_ns and self._replay_refusal() is None:
                # an armed autopilot is only asked: EKF3 on external nav takes a new origin in flight, which moves
                # every global position it holds (home and mission stay put in latitude/longitude, so RTL flies
                # elsewhere) where it had another one (a GPS start, a ground station's): a review's note
                if self._ap_armed:
                    self._request_origin()
                    self._origin_owed = True
                else:
                    self._send_origin()
                self._origin_left -= 1
                self._next_origin_ns = now + 1_000_000_000
                if self._origin_left == 0:
                    log.warning("autopilot did not confirm the EKF origin after %d tries (no GPS_GLOBAL_ORIGIN)%s: "
                                "set it from the ground station, or GUIDED/AUTO take-off may be refused",
                                ORIGIN_MAX_SENDS, "; it is armed, so it was only asked, not set in flight (set once "
                                "it is disarmed)" if self._ap_armed else "")
            self._recheck_origin(now)
            if now >= self._next_send_ns:
                with self._pending_lock:
                    state, self._pending = self._pending, None
                max_age = self._max_age_ns  # once: send_state (another thread) may turn it off
                if state is not None and max_age is not None and now - state.t_ns > max_age:
                    self.stats.states_too_old += 1  # aged while it waited (this thread stalled): dropped
                    state = None
                if state is not None and not state.tracking and self._continue_frame:
                    # a start in flight chooses its frame at the first tracked pose sent: a lost pose before it went
                    # out in this process's own frame and the next tracked one in the autopilot's, one reset_counter
                    # (a review's finding: PX4 fuses any quality at EKF2_EV_QMIN 0)
                    self.stats.states_not_tracking += 1
                    state = None
                refusing = self._replay_refusal()
                if state is not None and refusing:
                    # unheard (before its first heartbeat, or silent past link_timeout_s) it may be armed: a
                    # replay's first poses went out before the heartbeat that said so
                    if refusing == "armed":
                        self._refuse_armed()
                    else:
                        self._refuse_unheard()
                    self._refusing = refusing
                    state = None
                elif self._refusing is not None:
                    # no pose to send (the recording ended, tracking lost): the reason as it is now, None once heard
                    # disarmed; the status said "poses not sent ... armed" until the next pose, which may never come
                    self._refusing = refusing
                if state is not None:
                    self._refusing = None
                    self._next_send_ns = _next_slot(self._next_send_ns, self._period_ns, now)
                    self._send_state_messages(state, now)

    # ---------------------------------------------------------------- messages

    def build_messages(self, state: NavState) -> list:
        """The configured pose messages for one state (pymavlink message objects, not yet packed)."""
        if self.T_frd_body is None:
            raise VioError("the IMU mount is not known yet: call set_camera_mount() (mount = camera-*)")
        od = to_vehicle_odometry(state.t_ns, state.T_world_body, state.v_world, state.omega_body,
                                 state.cov_pose, state.cov_vel, self.T_frd_body)
        if state.tracking or self._align is not None:
            od = self._in_autopilot_frame(od)
        usec = state.t_ns // 1000
        reset = self._sent_counter(state)
        pose_cov = upper_triangle(od.cov_pose_ned)
        out = []
        for name in self.cfg.messages:
            if name == "VISION_POSITION_ESTIMATE":
                out.append(mavlink.MAVLink_vision_position_estimate_message(
                    usec, *od.p_ned, *od.rpy, pose_cov, reset))
            elif name == "VISION_SPEED_ESTIMATE":
                out.append(mavlink.MAVLink_vision_speed_estimate_message(
                    usec, *od.v_ned, [float(x) for x in od.cov_v_ned.ravel()], reset))
            elif name == "ODOMETRY":
                vel_cov = np.zeros((6, 6))
                vel_cov[:3, :3] = od.cov_v_frd
                vel_cov[3:, 3:] = np.diag([np.nan] * 3)  # angular-rate variance: not estimated
                out.append(mavlink.MAVLink_odometry_message(
                    usec, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, *od.p_ned,
                    [float(x) for x in od.q_ned_frd_wxyz], *od.v_frd, *od.omega_frd, pose_cov,
                    upper_triangle(vel_cov), reset, mavlink.MAV_ESTIMATOR_TYPE_VIO,
                    int(min(max(state.quality, 1), 100)) if state.tracking else self._lost_quality))
        return out

    def _sent_counter(self, state: NavState) -> int:
        """The reset_counter `state` goes out with: the estimator's, past where this process started and the resets
        forced here, mod 256."""
        return (state.reset_counter + self._reset_offset) % 256

    def _first_counter(self) -> int:
        """The reset_counter this process starts at: one past the last one sent before (a restart in flight moves
        to a new origin, and an unchanged counter would have the autopilot fuse the jump as a measurement), or a
        random one when none is known (a fresh state folder; the autopilot may still hold our last one)."""
        p = self._counter_file
        if p is None and not self._random_first_counter:
            return 0
        if p is None:  # `counter_file = ""`: started at 0 on every start, so a restart in flight re-sent the last
            start = secrets.randbelow(256)  # run's counter (a QA sweep); the config's help says a random start
            log.info("reset_counter starts at %d, a random value ([mavlink] counter_file is empty)", start)
            return start
        try:
            last = int(p.read_text().strip())
            if not 0 <= last <= 255:
                raise ValueError(f"{last} is not 0-255")
            start = (last + 1) % 256
            # taken only if this start can be kept in its place: a file left behind by a process that could not
            # write its later counters (a full or read-only disk) is stale, and its next value may be the very one
            # the autopilot last got (a review's finding)
            self._keep_counter(start)
            if self._counter_file is not None:
                log.info("reset_counter starts at %d: the last one sent before was %d (%s)", start, last, p)
                return start
            why = "the file cannot be written, so what it says may be stale"
        except FileNotFoundError:
            why = "none kept yet"
        except (OSError, ValueError) as e:
            why = f"cannot read it: {getattr(e, 'strerror', None) or e}"
        start = secrets.randbelow(256)
        log.info("reset_counter starts at %d, a random value (%s: %s)", start, p, why)
        return start

    def _keep_counter(self, value: int) -> None:
        """Write the reset_counter about to be sent to `counter_file` when it changes (resets and loop jumps: rare),
        before the messages carrying it: a process killed between the two still restarts past it. Written and
        renamed, not synced: a crash or a watchdog restart keeps the page cache, and an fsync on a busy SD card
        would hold the pose messages for up to seconds at exactly this moment (a power cut restarts the companion,
        and a counter kept there by then is one of 256 anyway)."""
        p = self._counter_file
        if p is None or value == self._counter_saved:
            return
        try:
            replace_atomically(p, lambda f: f.write(f"{value}\n".encode()), durable=False)
            self._counter_saved = value
        except OSError as e:
            # what is kept there is stale from now on: gone if it can be removed (a full disk), else a restart
            # finds that it cannot write it back and starts at a random value (_first_counter)
            with contextlib.suppress(OSError):
                p.unlink()
            log.warning("cannot keep the reset_counter in %s (%s): a restart will start at a random one", p,
                        e.strerror or e)
            self._counter_file = None

    def _send_state_messages(self, state: NavState, now: int) -> None:
        if self._last_reset_counter is not None and state.reset_counter != self._last_reset_counter:
            if state.loop_jumps - self._last_loop_jumps == state.reset_counter - self._last_reset_counter:
                # [loop] output = jump: the loop-corrected pose stepped, the estimator did not reset
                log.info("loop correction: position/yaw step, reset_counter %d -> %d (sent as %d)",
                         self._last_reset_counter, state.reset_counter,
                         self._sent_counter(state))
                self._statustext(mavlink.MAV_SEVERITY_INFO, "VIO loop correction")
            else:
                log.info("estimator reset: reset_counter %d -> %d (sent as %d)", self._last_reset_counter,
                         state.reset_counter, self._sent_counter(state))
                self._statustext(mavlink.MAV_SEVERITY_INFO, "VIO reset")
        self._last_reset_counter = state.reset_counter
        self._last_loop_jumps = state.loop_jumps
        if state.tracking and math.isnan(self.stats.first_tilt_deg):
            self._check_mount(state)
        self._keep_counter(self._sent_counter(state))
        for msg in self.build_messages(state):
            if not self._send(msg, msg.get_type()):
                return
        self._last_sent_t_ns = state.t_ns
        self._counter_sent = self._sent_counter(state)
        self.stats.states_sent += 1
        self.stats.last_latency_ms = (now - state.t_ns) / 1e6

    def _check_mount(self, state: NavState) -> None:
        """Say once when the first pose puts the vehicle far from level: the mount is then most likely wrong,
        and a wrong mount turns the autopilot's axes (forward flown as down). Poses still go out: the vehicle
        may really be leaning (a replay started in flight), and the operator decides."""
        R_world_frd = np.asarray(state.T_world_body, dtype=float)[:3, :3] @ self.T_frd_body[:3, :3].T
        # the vehicle's down axis against the world's down (world z is up)
        tilt = float(np.degrees(np.arccos(np.clip(-R_world_frd[2, 2], -1.0, 1.0))))
        self.stats.first_tilt_deg = round(tilt, 1)
        if tilt > MOUNT_TILT_WARN_DEG:
            log.warning("the vehicle is %.0f deg from level at its first pose: if it stands level, [mavlink] mount "
                        "(%r) is wrong and the autopilot would fly these axes turned; check it before take-off",
                        tilt, self.cfg.mount)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"VIO: {tilt:.0f} deg tilt at start: check mount")
        elif tilt > MOUNT_TILT_NOTE_DEG:
            # a camera tilt left out of the config reads as the vehicle pitched (22 deg on the EuRoC bench set-up,
            # said nowhere: a review's finding); a vehicle on uneven ground leans too, so the log only
            log.warning("the vehicle is %.0f deg from level at its first pose: if it stands level, set [mavlink] "
                        "camera_tilt_deg (or mount_rpy_deg) to the camera's tilt; the attitude sent is off by it", tilt)

    def _recheck_origin(self, now: int) -> None:
        """While the autopilot is heard disarmed, ask for the origin it confirmed every ORIGIN_RECHECK_NS; unanswered
        for ORIGIN_ANSWER_NS, it was dropped (an EKF that initialised after confirming it): set it again, once per
        loss, with the usual ORIGIN_MAX_SENDS tries."""
        if self._origin_recheck_ns is None:
            return
        if self._ap_armed or not self._link_up:  # an answer missed then is no loss: ask again once disarmed
            self._origin_asked_ns = None
            return
        if self._origin_asked_ns is not None and now - self._origin_asked_ns > ORIGIN_ANSWER_NS:
            self.stats.origin_lost += 1
            log.warning("the autopilot no longer reports the EKF origin it confirmed (no GPS_GLOBAL_ORIGIN %.0f s "
                        "after asking; its EKF initialised again?): setting it again", ORIGIN_ANSWER_NS / 1e9)
            self._set_origin_again(now)
        elif self._origin_asked_ns is None and now >= self._origin_recheck_ns:
            self._origin_asked_ns, self._origin_recheck_ns = now, now + ORIGIN_RECHECK_NS
            self._request_origin()

    def _set_origin_again(self, now: int) -> None:
        """Send the origin and home until confirmed (after a link-up, a restart, a dropped origin)."""
        self._origin_left, self._next_origin_ns = ORIGIN_MAX_SENDS, now
        self._origin_owed = False
        self._origin_recheck_ns = self._origin_asked_ns = None
        self.stats.origin_confirmed = False

    def _origin_units(self) -> tuple[int, int, int]:
        """The configured origin in the messages' units: latitude and longitude [1e-7 deg], altitude [mm]."""
        return (int(round(self.cfg.origin_lat_deg * 1e7)), int(round(self.cfg.origin_lon_deg * 1e7)),
                int(round(self.cfg.origin_alt_m * 1000)))

    def _origin_is_ours(self, msg: Any) -> bool:
        """Whether a GPS_GLOBAL_ORIGIN is the configured origin (to a unit of 1e-7 deg, and the cm ArduPilot keeps)."""
        lat, lon, alt_mm = self._origin_units()
        return (abs(int(msg.latitude) - lat) <= 1 and abs(int(msg.longitude) - lon) <= 1
                and abs(int(msg.altitude) - alt_mm) <= 10)  # ArduPilot keeps cm

    def _request_origin(self) -> None:
        # an autopilot that already had the origin does not resend it unasked; one without an origin sends nothing
        self._send(mavlink.MAVLink_command_long_message(
            self.target_system, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
            float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN), 0, 0, 0, 0, 0, 0), "COMMAND_LONG")

    def _send_origin(self) -> None:
        lat, lon, alt_mm = self._origin_units()
        self._send(mavlink.MAVLink_set_gps_global_origin_message(self.target_system, lat, lon, alt_mm, 0),
                   "SET_GPS_GLOBAL_ORIGIN")
        # not to an armed autopilot: it set its home where it armed (ArduCopter moves an unlocked home to the vehicle
        # at arming), and RTL flies there; a link lost and back in flight moved it to this origin (a review's finding)
        if not self._ap_armed:
            self._send(mavlink.MAVLink_set_home_position_message(
                self.target_system, lat, lon, alt_mm, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0),
                "SET_HOME_POSITION")
        self._request_origin()  # the confirmation

    def _check_estimates_stopped(self, now: int) -> None:
        """Tracking is lost too when no estimate arrives at all (NO_ESTIMATE_LOST_NS): with the camera and the IMU
        gone together no state says tracking = false, and the autopilot heard nothing, not even to land."""
        with self._pending_lock:
            last = self._last_state_at_ns
            stopped = bool(self._tracking) and last is not None and now - last >= NO_ESTIMATE_LOST_NS
            if stopped:
                self._tracking, self._lost_since_ns, self._land_done, self._pending = False, last, False, None
        if stopped:
            log.warning("no estimate for %.1f s (the sensors silent, or the estimator stopped or behind)",
                        (now - last) / 1e9)
            self._on_tracking_change(False)

    def _check_land_after_loss(self, now: int) -> None:
        """With land_after_loss_s: once tracking has been lost that long and the autopilot is armed, ask it
        to LAND where it is. Why here and not only in the autopilot: with vision gone its EKF dead-reckons on
        the IMU and holds a position that drifts away (0.9-2.7 m in 10 s in the SITL test) until its variance
        reaches FS_EKF_THRESH (8 s there); a LAND after a few seconds comes down near where vision was lost."""
        if self.cfg.land_after_loss_s <= 0 or not self._poses_to_armed:
            # a replay (poses_to_armed False) is another flight's: its loss, or its end, is not this vehicle's,
            # and with the flight's own configuration it asked an armed autopilot to LAND
            return
        # decided and marked under the lock send_state() takes: tracking regained between the two must neither
        # get a LAND nor leave this loss marked done for the next one (a review's finding: the failsafe was off)
        with self._pending_lock:
            lost_ns = self._lost_since_ns
            due = (not self._land_done and lost_ns is not None and self._ap_armed and self._link_up
                   and now - lost_ns >= self.cfg.land_after_loss_s * 1e9)
            if due:
                self._land_done, self._land_left, self._next_land_ns = True, LAND_MAX_SENDS, now
            elif self._tracking:
                self._land_left = 0  # tracking is back: the LAND already sent stands, no more of them
        if due:
            self.stats.land_accepted = False
            log.warning("tracking lost for %.1f s: asking the autopilot to LAND (land_after_loss_s = %g)",
                        (now - lost_ns) / 1e9, self.cfg.land_after_loss_s)
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, "VIO lost: LAND requested")
        if self._land_left > 0 and (self.stats.land_accepted or not self._ap_armed):
            self._land_left = 0
        if self._land_left > 0 and now >= self._next_land_ns:
            # lat/lon NaN: land at the current position (PX4); ArduCopter switches to LAND mode
            self._send(mavlink.MAVLink_command_long_message(
                self.target_system, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, math.nan, math.nan, math.nan, 0),
                "COMMAND_LONG")
            self.stats.land_requests += 1
            self._land_left -= 1
            self._next_land_ns = now + 1_000_000_000
            if self._land_left == 0 and not self.stats.land_accepted:
                log.warning("autopilot did not acknowledge LAND after %d requests: land it from the ground "
                            "station", LAND_MAX_SENDS)
                self._statustext(mavlink.MAV_SEVERITY_CRITICAL, "VIO lost, LAND not acked: land it")

    def _armed_before_any_pose(self, now: int) -> None:
        """The autopilot is armed when this process first hears it, and no pose has gone out yet: started (or
        restarted by systemd) in flight, or a companion that came up after take-off. A loss that began before the
        first pose never started the loss clock: no word to the ground station while the autopilot dead-reckoned
        (a QA sweep). It is said now (STATUSTEXT, log) and counts as lost until the first tracked pose; no LAND is
        asked for it: nothing here tells a vehicle that was flying on our poses from one flown without them (on
        GPS, by hand), which a LAND would take from its pilot (a review's finding). The autopilot's own failsafe
        acts on its side; a loss after this process has tracked gets land_after_loss_s as ever."""
        with self._pending_lock:
            if self._tracked_frame is not None or self._lost_since_ns is not None or self._frame_kept:
                return
            self._tracking, self._lost_since_ns, self._land_done = False, now, True
        log.warning("the autopilot is armed and this process has sent no pose yet (started or restarted in "
                    "flight?): not tracking; no LAND is asked for it")
        self._tracking_text("VIO not tracking (restarted?)", mavlink.MAV_SEVERITY_WARNING)
        self._continue_frame = True
        self._ask_ap_pose(1e6 / AP_POSE_RATE_HZ)

    def _ask_ap_pose(self, interval_us: float) -> None:
        """Set the autopilot's LOCAL_POSITION_NED and ATTITUDE interval (0: its default), read at a start in flight."""
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self._send(mavlink.MAVLink_command_long_message(
                self.target_system, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us,
                0, 0, 0, 0, 0), "COMMAND_LONG")

    def _in_autopilot_frame(self, od: VehicleOdometry) -> VehicleOdometry:
        """`od` (a tracked state's vehicle odometry) in the autopilot's frame after a start in flight: decided at the
        first tracked pose (the autopilot's estimate no older than AP_POSE_MAX_AGE_NS, else our own frame, said),
        then the same turn and shift for every pose of this process."""
        if self._continue_frame:
            self._continue_frame = False
            now = self._clock()
            local, yaw = self._ap_local, self._ap_yaw
            self._ask_ap_pose(0)  # read once: their rate back to the autopilot's default (it costs link bandwidth)
            if local is None or yaw is None or now - min(local[0], yaw[0]) > AP_POSE_MAX_AGE_NS:
                log.warning("started in flight, but the autopilot's own position and attitude did not arrive "
                            "(LOCAL_POSITION_NED, ATTITUDE): poses start a new frame, and the autopilot's position "
                            "jumps to it at the reset_counter change")
            else:
                # the autopilot's estimate carried to our pose's stamp along its own velocity and yaw rate: taken
                # as it was on arrival, up to AP_POSE_MAX_AGE_NS older than our pose, it put the frame v * age off
                # for the rest of the flight (0.25-0.5 m at 5 m/s; a review's finding)
                # a pose stamp seconds off this host's clock is on another (a sensor's own; max_state_age_ms off):
                # its difference said nothing, and clamped it carried the estimate 0.5 s (2.5 m at 5 m/s, a
                # review's finding); carried to now then, where the pose is being sent
                t_pose = od.t_ns if abs(od.t_ns - now) <= ANOTHER_CLOCK_NS else now
                carry_ns = _clamped_age_ns(t_pose - local[0])
                p_ap = local[1] + local[2] * (carry_ns * 1e-9)
                yaw_ap = yaw[1] + yaw[2] * (_clamped_age_ns(t_pose - yaw[0]) * 1e-9)
                dyaw = math.remainder(yaw_ap - float(od.rpy[2]), math.tau)
                c, s_ = math.cos(dyaw), math.sin(dyaw)
                R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
                shift = p_ap - R @ od.p_ned
                self._align = (R, shift, dyaw)
                log.info("started in flight: poses continue in the autopilot's frame (its estimate at "
                         "%.2f, %.2f, %.2f m NED, yaw %.1f deg, carried %.0f ms to our pose at its %.1f m/s; ours "
                         "turned %.1f deg and shifted %.2f m)", *p_ap, math.degrees(yaw_ap),
                         carry_ns * 1e-6, float(np.linalg.norm(local[2])), math.degrees(dyaw),
                         float(np.linalg.norm(shift)))
        if self._align is None:
            return od
        R, shift, dyaw = self._align
        J = np.eye(6)
        J[:3, :3] = R
        R_ned_frd = R @ od.R_ned_frd
        rpy = np.array([od.rpy[0], od.rpy[1], math.remainder(float(od.rpy[2]) + dyaw, math.tau)])
        return dataclasses.replace(od, p_ned=R @ od.p_ned + shift, R_ned_frd=R_ned_frd, rpy=rpy,
                                   q_ned_frd_wxyz=rot_to_quat_wxyz(R_ned_frd), v_ned=R @ od.v_ned,
                                   cov_pose_ned=J @ od.cov_pose_ned @ J.T, cov_v_ned=R @ od.cov_v_ned @ R.T)

    def _replay_refusal(self) -> str | None:
        """Why a pose of this output would be withheld now: "armed", "unheard" (no heartbeat within link_timeout_s
        says disarmed), or None (sent; always None with poses_to_armed)."""
        if self._poses_to_armed or not (self._ap_armed or not self._link_up):
            return None
        return "armed" if self._ap_armed else "unheard"

    def _refuse_armed(self) -> None:
        """A pose not sent: this output replays a recording and the autopilot says it is armed (said once, in the
        log and to the ground station)."""
        self.stats.states_refused_armed += 1
        if not self._armed_refusal_said:
            self._armed_refusal_said = True
            log.error("the autopilot is armed: no pose of this replay is sent while it is (a recording's or a "
                      "simulation's poses are another flight's, not this vehicle's; replay to a disarmed autopilot "
                      "on the bench or a SITL before arming, or fly with vio run and a live [source])")
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, "VIO replay: armed, poses not sent")

    def _refuse_unheard(self) -> None:
        """A replay's pose not sent: no autopilot heartbeat (within link_timeout_s) says it is disarmed."""
        self.stats.states_refused_unheard += 1
        if not self._unheard_refusal_said:
            self._unheard_refusal_said = True
            log.warning("no autopilot heartbeat says it is disarmed: no pose of this replay is sent until one does")

    def _statustext(self, severity: int, text: str) -> None:
        self._send(mavlink.MAVLink_statustext_message(severity, text.encode()[:50]), "STATUSTEXT")

    def _on_tracking_change(self, tracking: bool) -> None:
        """One log line and STATUSTEXT per change, unless tracking flaps (FLAP_CHANGES changes within
        FLAP_WINDOW_S, e.g. frames arriving in bursts on an overloaded board): then one "unstable" message,
        and the next one only once the state has held for FLAP_WINDOW_S (sent from poll())."""
        now = self._clock()
        self._changes = [t for t in self._changes if now - t < FLAP_WINDOW_NS] + [now]
        if len(self._changes) >= FLAP_CHANGES:
            if not self._flapping:
                self._flapping = True
                log.warning("tracking unstable: %d losses/regains in %.0f s; pose output follows each",
                            len(self._changes), FLAP_WINDOW_NS / 1e9)
                self._tracking_text("VIO tracking unstable", mavlink.MAV_SEVERITY_WARNING)
            return
        self._announce_tracking(tracking)

    def _announce_tracking(self, tracking: bool) -> None:
        if tracking:
            log.info("tracking regained: pose output resumes")
        else:
            log.warning("tracking lost: pose output paused")
        self._tracking_text("VIO tracking regained" if tracking else "VIO tracking lost",
                            mavlink.MAV_SEVERITY_INFO if tracking else mavlink.MAV_SEVERITY_WARNING)

    def _tracking_text(self, text: str, severity: int) -> None:
        with self._lock:
            # a replay's tracking is another flight's: not said on an armed vehicle's ground station (a "VIO
            # tracking lost" there, spoken aloud by QGC / Mission Planner, is of a vehicle not flying on it)
            if self.connected and self._replay_refusal() != "armed":
                self._statustext(severity, text)

    def _check_flapping(self, now: int) -> None:
        """End the unstable period once the tracking state held for FLAP_WINDOW_S; say where it ended."""
        if self._flapping and self._changes and now - self._changes[-1] >= FLAP_WINDOW_NS:
            self._flapping = False
            self._changes = []
            self._announce_tracking(bool(self._tracking))

    # ---------------------------------------------------------------- link

    def _on_link_message(self, msg: Any, t_arrival_ns: int) -> None:
        """Link mode (its reader thread): queue the message and wake our thread, which answers promptly."""
        self._inbox.append(msg)
        self._wake()

    def _read_incoming(self, now: int) -> None:
        for _ in range(100):  # bounded: a flood of input must not starve our output
            try:
                if self._link is not None:
                    msg = self._inbox.popleft() if self._inbox else None
                else:
                    msg = self._conn.recv_match(blocking=False)
            except Exception as e:  # serial unplugged, socket reset: pyserial/socket raise various types
                self._io_failed(e)
                return
            if msg is None:
                return
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                # once locked on, only the locked autopilot's heartbeats keep the link up; another system's
                # (a second vehicle on a shared radio) takes over only after ours has been silent the timeout
                locked = self._last_ap_heartbeat_ns is not None and now - self._last_ap_heartbeat_ns < self._timeout_ns
                if not is_autopilot_heartbeat(msg, self.target_system if locked else None):
                    self.stats.other_heartbeats += 1
                    continue
                self._last_ap_heartbeat_ns = now
                self.stats.autopilot_heartbeats += 1
                self._ap_armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                if not self._ap_armed and self._origin_owed and self._origin_left == 0:
                    # a flight longer than ORIGIN_MAX_SENDS tries spent them all asking; nothing set it after
                    # landing, for the next take-off (a review's finding)
                    log.info("autopilot disarmed: setting the EKF origin it did not confirm in flight")
                    self._set_origin_again(now)
                if self._ap_armed and self.stats.autopilot_heartbeats == 1 and self._poses_to_armed:
                    self._armed_before_any_pose(now)
                booting = msg.system_status in BOOTING_STATES
                if booting and self._ap_running and locked:
                    self._autopilot_restarted(now, "its heartbeat says it is booting")
                    self._ap_ts1 = None  # its next TIMESYNC starts the new clock, not a second restart
                self._ap_running = not booting
                if self._lost_as_quality0 and msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 and not self._px4_said:
                    # PX4 fuses any quality while EKF2_EV_QMIN <= 0 (its default): a lost pose with -1 or 0 too
                    self._px4_said = True
                    log.warning("the autopilot is PX4: with lost_output = %r set EKF2_EV_QMIN = 1, or it fuses the "
                                "poses sent while lost (it takes any quality at its default 0)", self.cfg.lost_output)
                sysid = msg.get_srcSystem()
                if sysid != self.target_system or (self.cfg.system_id == 0 and sysid != self.system_id):
                    log.info("autopilot is system %d; sending as %d/%d", sysid,
                             self.cfg.system_id or sysid, OUR_COMPONENT)
                    self.target_system = sysid
                    if self.cfg.system_id == 0:
                        self.system_id = sysid
                        if self._link is not None:
                            self._link.set_source_system(sysid)
                        else:
                            self._conn.mav.srcSystem = sysid
            elif kind in ("LOCAL_POSITION_NED", "ATTITUDE") and not self._from_autopilot(msg):
                continue  # another component of its system (a second estimator, a companion program): not its own
            elif kind == "LOCAL_POSITION_NED":
                self._ap_local = (now, np.array([msg.x, msg.y, msg.z], dtype=float),
                                  np.array([msg.vx, msg.vy, msg.vz], dtype=float))
            elif kind == "ATTITUDE":
                self._ap_yaw = (now, float(msg.yaw), _yaw_rate(msg))
            elif kind == "GPS_GLOBAL_ORIGIN" and self._from_autopilot(msg):  # not another component's repeat
                self._origin_asked_ns = None  # a recheck answered (or the first confirmation)
                if self._origin_left > 0:
                    self._origin_left, self._origin_owed = 0, False
                    self._origin_recheck_ns = now + ORIGIN_RECHECK_NS
                    self.stats.origin_confirmed = True
                    log.info("autopilot confirmed the EKF origin (%.7f, %.7f, %.1f m)", msg.latitude * 1e-7,
                             msg.longitude * 1e-7, msg.altitude * 1e-3)
                    self.stats.origin_ours = self._origin_is_ours(msg)
                    if not self.stats.origin_ours:
                        log.warning("the autopilot's EKF origin (%.7f, %.7f, %.1f m) is not [mavlink] origin_lat_deg/"
                                    "origin_lon_deg/origin_alt_m (%.7f, %.7f, %.1f m)%s", msg.latitude * 1e-7,
                                    msg.longitude * 1e-7, msg.altitude * 1e-3, self.cfg.origin_lat_deg,
                                    self.cfg.origin_lon_deg, self.cfg.origin_alt_m,
                                    ": kept, it is armed (an origin is not changed in flight)" if self._ap_armed
                                    else "")
            elif (kind == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_NAV_LAND and self._land_done
                  and self._from_autopilot(msg)):  # another component's ACK stopped the repeats
                accepted = msg.result == mavlink.MAV_RESULT_ACCEPTED
                if accepted and not self.stats.land_accepted:
                    log.info("autopilot accepted LAND")
                elif not accepted:
                    log.warning("autopilot refused LAND (COMMAND_ACK result %d)", msg.result)
                self.stats.land_accepted = self.stats.land_accepted or accepted
            elif kind == "TIMESYNC" and msg.tc1 == 0 and (self._last_ap_heartbeat_ns is None or (
                    msg.get_srcSystem() == self.target_system
                    and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1)):
                # A request from the autopilot (others' requests are theirs to answer: a second answer from us
                # would spoil their round trip): answer with our clock (the one NavState.t_ns uses), echo its ts1.
                self._send(mavlink.MAVLink_timesync_message(time.monotonic_ns(), msg.ts1), "TIMESYNC")
                self.stats.timesync_answered += 1
                if self._last_ap_heartbeat_ns is not None:
                    last, self._ap_ts1 = self._ap_ts1, int(msg.ts1)
                    if last is not None and msg.ts1 < last - RESTART_CLOCK_BACK_NS:
                        self._autopilot_restarted(now, f"its clock went back from {last / 1e9:.1f} s to "
                                                       f"{msg.ts1 / 1e9:.1f} s since boot")
                        self._ap_running = False  # a booting heartbeat after this is the same restart

    def _from_autopilot(self, msg: Any) -> bool:
        """Is `msg` the autopilot's own (its system, component 1)? Its estimate places a start in flight's poses, its
        COMMAND_ACK stops the LAND requests and its GPS_GLOBAL_ORIGIN confirms the origin: another component's of its
        system put every pose of the process in that one's frame, or stopped them unsent (review notes)."""
        return msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1

    def _autopilot_restarted(self, now: int, why: str) -> None:
        """The autopilot rebooted without the link going down: it has lost the EKF origin we set, which is sent
        again until confirmed. A LAND request is not repeated: a rebooted autopilot comes back disarmed, and one that
        recovered armed in flight has a pilot or a failsafe of its own (a LAND re-sent on a false restart would
        override a pilot who took over)."""
        self.stats.autopilot_restarts += 1
        origin = math.isfinite(self.cfg.origin_lat_deg) and math.isfinite(self.cfg.origin_lon_deg)
        log.warning("the autopilot restarted (%s)%s", why, ": setting the EKF origin again" if origin else "")
        if origin:
            self._set_origin_again(now)

    def _update_link(self, now: int) -> None:
        up = self._last_ap_heartbeat_ns is not None and now - self._last_ap_heartbeat_ns < self._timeout_ns
        if up and not self._link_up:
            log.info("autopilot link up (system %d) on %s", self.target_system, self.url)
            if math.isfinite(self.cfg.origin_lat_deg) and math.isfinite(self.cfg.origin_lon_deg):
                self._set_origin_again(now)
        elif self._link_up and not up:
            self.stats.link_losses += 1
            log.warning("autopilot link lost: no heartbeat for %.1f s", self.cfg.link_timeout_s)
        self._link_up = up

    def _send(self, msg: object, name: str) -> bool:
        if self._link is not None:
            if not self._link.send(msg):  # the link counts and logs its own errors and reconnects
                return False
            self.stats.sent[name] = self.stats.sent.get(name, 0) + 1
            return True
        if self._conn is None:
            return False
        try:
            self._conn.mav.send(msg)
        except UNPACKABLE as e:  # the message, not the connection
            unpackable(msg, e, self._unpackable_said)
            return False
        except Exception as e:
            self._io_failed(e)
            return False
        if getattr(self._conn, "portdead", False):  # mavutil's serial write swallows the error
            self._io_failed(OSError("serial write failed"))
            return False
        self.stats.sent[name] = self.stats.sent.get(name, 0) + 1
        return True

    def _open(self) -> bool:
        try:
            self._conn = open_connection(self.url, self.system_id)
        except VioError:
            raise
        except Exception as e:
            self._conn = None
            self._reopen_at_ns = self._clock() + int(self._backoff_s * 1e9)
            if not self._conn_failed_logged:
                log.warning("cannot open %s (%s); retrying every <= %.0f s", self.url, e, RECONNECT_MAX_S)
                self._conn_failed_logged = True
            else:
                log.debug("cannot open %s: %s", self.url, e)
            self._backoff_s = min(self._backoff_s * 2, RECONNECT_MAX_S)
            return False
        if self._conn_failed_logged:
            log.info("reconnected to %s", self.url)
            self.stats.reconnects += 1
        self._conn_failed_logged = False
        self._backoff_s = RECONNECT_MIN_S
        return True

    def _io_failed(self, e: Exception) -> None:
        self.stats.io_errors += 1
        if not self._conn_failed_logged:
            log.warning("link error on %s (%s: %s); reconnecting", self.url, type(e).__name__, e)
            self._conn_failed_logged = True
        self._close_conn()
        self._reopen_at_ns = self._clock() + int(self._backoff_s * 1e9)

    def _close_conn(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception as e:  # closing a dead port may fail too; nothing left to do
                log.debug("close failed: %s", e)
            self._conn = None

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll()
            except Exception:  # keep the output alive; the next poll reconnects if needed
                log.exception("mavlink output step failed")
            now = self._clock()
            wake = min(self._next_heartbeat_ns, now + 100_000_000)
            if self._pending is not None:
                wake = min(wake, self._next_send_ns)
            timeout_s = max(wake - now, 100_000) / 1e9
            fd = getattr(self._conn, "fd", None)
            fds = [self._wake_r] if fd is None else [self._wake_r, fd]
            if fd is None and self._link is None:  # a link's reader wakes us through the pipe
                timeout_s = min(timeout_s, 0.005)  # no pollable fd: check the input every 5 ms
            # Wake on incoming bytes too: PX4 drops TIMESYNC round trips slower than ~10 ms.
            with contextlib.suppress(OSError, ValueError):
                select.select(fds, [], [], timeout_s)
            with contextlib.suppress(OSError):
                os.read(self._wake_r, 4096)


def restamp_to_host_clock(sink: Callable[[NavState], object]) -> Callable[[NavState], None]:
    """Wrap a sink so that replayed states (dataset time) carry host CLOCK_MONOTONIC stamps like live ones.

    The offset is fixed at the first state, so a real-time replay keeps its spacing; TIMESYNC answers and
    time_usec then share one clock, as PX4 requires.
    """
    offset: list[int] = []

    def push(state: NavState) -> None:
        if not offset:
            offset.append(time.monotonic_ns() - state.t_ns)
        sink(dataclasses.replace(state, t_ns=state.t_ns + offset[0]))
    return push


def _yaw_rate(att: Any) -> float:
    """The rate of ATTITUDE's yaw angle [rad/s]: its rollspeed/pitchspeed/yawspeed are body rates, and the yaw angle
    turns at (q sin(roll) + r cos(roll)) / cos(pitch) (yawspeed alone read a 30 deg banked turn 13 % slow: a
    review's note); near +-90 deg of pitch, where yaw is undefined, yawspeed."""
    c = math.cos(att.pitch)
    if abs(c) < 0.1:
        return float(att.yawspeed)
    return float((att.pitchspeed * math.sin(att.roll) + att.yawspeed * math.cos(att.roll)) / c)


def _clamped_age_ns(dt_ns: int) -> int:
    """How far the autopilot's estimate is carried to our pose's stamp: at most AP_POSE_MAX_AGE_NS either way (a
    stamp further off is not extrapolated along a velocity that old)."""
    return max(-AP_POSE_MAX_AGE_NS, min(AP_POSE_MAX_AGE_NS, int(dt_ns)))


def _next_slot(slot_ns: int, period_ns: int, now_ns: int) -> int:
    """Next slot of a fixed grid (no drift from late wake-ups); re-anchor after a gap of a whole period."""
    nxt = slot_ns + period_ns
    return nxt if nxt > now_ns else now_ns + period_ns
