"""What the daemon needs of its collaborators, as typed Protocols instead of attribute probing.

The real ones are `drivers.base.SensorSource`, `vio.estimator.Estimator` and
`drivers.mavlink_out.MavlinkOutput`; tests pass stand-ins of the same shape. A collaborator that lacks a
member fails at once with an AttributeError naming it, not with a silently different behaviour.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from vio.types import FeatureFrame, ImuSample, NavState, StereoFrame

if TYPE_CHECKING:
    from vio.calibration import StereoCalibration
    from vio.estimator import EstimatorHealth, ProcessedFrame


class Source(Protocol):
    """A sensor source (drivers.base.SensorSource)."""

    @property
    def finished(self) -> bool: ...  # a finite source (dataset, fake with a duration) is done

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def poll(self) -> list[ImuSample | StereoFrame]: ...

    def calibration(self) -> StereoCalibration | None: ...

    def health(self) -> dict[str, Any]: ...

    def stamp_uncertainty_s(self) -> float: ...  # how far its IMU stamps may be off the host clock [s]


class EstimatorApi(Protocol):
    """The estimator (vio.estimator.Estimator)."""

    last_features: FeatureFrame | None  # of the newest processed frame (status: track count)
    last_frame_stamp_ns: int | None  # the stamp it gave the frame fed last (restamped: vio.frame_clock)

    def feed_imu(self, s: ImuSample) -> NavState | None: ...

    def feed_frame(self, frame: StereoFrame) -> NavState | None: ...

    def reset(self, reason: str, bridge: bool = True, keep_bias: bool | None = None) -> None: ...

    def health(self) -> EstimatorHealth: ...

    def take_processed(self) -> list[ProcessedFrame]: ...  # frames finished since the last call

    def stop_for_run(self, problem: str) -> None: ...  # a replaced estimator's verdict on the IMU, kept


class PoseOutput(Protocol):
    """The MAVLink output (drivers.mavlink_out.MavlinkOutput)."""

    @property
    def link_up(self) -> bool: ...

    @property
    def states_sent(self) -> int: ...

    def send_state(self, state: NavState) -> object: ...

    def withhold(self, why: str | None) -> None: ...  # no pose at all while `why` is set (said once to the GCS)

    def poll(self) -> None: ...

    def close(self, final: bool = True) -> None: ...

    def health(self) -> dict[str, Any]: ...

    def counters(self) -> dict[str, int]: ...  # its counts, which the daemon adds up over the outputs it reopens
