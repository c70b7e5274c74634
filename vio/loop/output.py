"""What the autopilot gets from loop closure (docs/autopilot.md#loop-closure): the odometry pose mapped with
the newest loop correction T_world_odom, delivered as `off` (the odometry, untouched), `jump` (the whole
correction at once, `reset_counter` incremented so that ArduPilot/PX4 re-reference instead of fighting the
jump) or `blend` (the applied correction walks towards the newest one at a bounded rate: position and yaw
move smoothly, reset_counter unchanged). Roll and pitch are never corrected (the IMU observes them)."""

from __future__ import annotations

import dataclasses

import numpy as np

from vio.geometry import make_T, roll_pitch_yaw, so3_exp
from vio.types import NavState


def _yaw_rot(yaw: float) -> np.ndarray:
    return so3_exp(np.array([0.0, 0.0, yaw]))


def _yaw_only(C: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation, yaw) of a correction; its roll/pitch part is dropped."""
    return C[:3, 3].copy(), float(roll_pitch_yaw(C[:3, :3])[2])


class CorrectedOutput:
    def __init__(self, mode: str = "off", blend_rate_m_s: float = 0.2, blend_rate_deg_s: float = 5.0) -> None:
        if mode not in ("off", "jump", "blend"):
            raise ValueError(f"loop output mode {mode!r}: expected off, jump or blend")
        self.mode = mode
        self.rate_m_s = blend_rate_m_s
        self.rate_rad_s = np.radians(blend_rate_deg_s)
        self._t = np.zeros(3)  # applied correction: translation and yaw
        self._yaw = 0.0
        self._version = 0  # of the correction applied (jump mode takes each new one)
        self.jumps = 0  # reset_counter increments added (jump mode)
        self._last_t_ns: int | None = None

    def apply(self, state: NavState, T_world_odom: np.ndarray, version: int) -> NavState:
        if self.mode == "off":
            return state
        target_t, target_yaw = _yaw_only(T_world_odom)
        dt = 0.0 if self._last_t_ns is None else max(state.t_ns - self._last_t_ns, 0) * 1e-9
        self._last_t_ns = state.t_ns
        if self.mode == "jump":
            if version != self._version:
                self._version = version
                if not (np.allclose(target_t, self._t) and np.isclose(target_yaw, self._yaw)):
                    self.jumps += 1
                self._t, self._yaw = target_t, target_yaw
        else:
            # Bounded where it matters, at the vehicle: the sent position moves by the correction at most
            # rate_m_s * dt per step. A yaw change turns the odometry about its origin, so bounding the translation
            # alone let a vehicle 20 m out move at 1.75 m/s under a 30 deg yaw correction (a review's finding).
            p = state.T_world_body[:3, 3]
            q_now = _yaw_rot(self._yaw) @ p + self._t  # where the applied correction sends the vehicle now
            dyaw = float(np.angle(np.exp(1j * (target_yaw - self._yaw))))
            self._yaw += float(np.clip(dyaw, -self.rate_rad_s * dt, self.rate_rad_s * dt))
            step = _yaw_rot(target_yaw) @ p + target_t - q_now
            n = float(np.linalg.norm(step))
            if n > self.rate_m_s * dt:
                step *= self.rate_m_s * dt / n
            self._t = q_now + step - _yaw_rot(self._yaw) @ p
        C = make_T(_yaw_rot(self._yaw), self._t)
        return dataclasses.replace(state, T_world_body=C @ state.T_world_body, v_world=C[:3, :3] @ state.v_world,
                                   reset_counter=state.reset_counter + self.jumps,
                                   loop_jumps=state.loop_jumps + self.jumps)
