"""Stereo visual front end: StereoFrame (+ gyro prior) -> FeatureFrame (see docs/frontend.md)."""

from vio.frontend.gyro import GyroPrior, integrate_gyro
from vio.frontend.tracker import StereoTracker

__all__ = ["GyroPrior", "StereoTracker", "integrate_gyro"]
