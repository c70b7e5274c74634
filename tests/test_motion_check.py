"""The motion check on its own (vio.motion_check): synthetic keyframes, the smoother's poses scripted."""

from __future__ import annotations

import numpy as np

from vio.backend.synthetic import Motion, SyntheticScene, synthetic_calibration
from vio.motion_check import MotionCheck, MotionTally


def test_a_runaway_is_confirmed_on_its_third_keyframe_and_the_anchor_is_where_the_stereo_pair_says():
    """The scripted runaway below (shared with the tally's test)."""
    _runaway()


def _runaway() -> MotionCheck:
    """Keyframes 0.3 s apart on a 1 m/s flight; from keyframe 4 the smoother's poses run away at 4 m/s more. The first
    four agree (0.5 px noise); keyframes 4, 5, 6 disagree, and the third in a row is the failure. The restart's anchor
    (the last trusted pose carried by the stereo displacements) is within centimetres of the camera, while the
    smoother's pose is 3.6 m off."""
    calib = synthetic_calibration()
    mot, scene, rng = Motion(speed=1.0, still_s=0.0, seed=3), SyntheticScene(calib, seed=3), np.random.default_rng(3)
    chk = MotionCheck(calib.cam0.K, calib.baseline_m, n_sigma=5.0, min_m_s=1.0, scale_sigma=0.1, confirm=3)
    said = []
    for k in range(7):
        t = 1.0 + 0.3 * k
        T_true = mot.pose(t) @ calib.cam0.T_body_cam
        T_est = T_true.copy()
        T_est[:3, 3] += [4.0 * 0.3 * max(k - 3, 0), 0.0, 0.0]
        said.append(chk.add(int(t * 1e9), scene.observe(int(t * 1e9), mot.pose(t), pixel_sigma=0.5, rng=rng), T_est))
        assert len(chk.streak) == max(k - 3, 0), (k, [r.describe() for r in chk.streak])
    assert said[:6] == [None] * 6 and said[6] is not None, said
    assert said[6].startswith("motion check: ") and "3 keyframes in a row" in said[6], said[6]
    gap = chk.streak[-1].gap_m_s
    assert 3.0 < gap < 5.0, chk.streak[-1].describe()
    assert np.linalg.norm(chk.stereo_anchor()[:3, 3] - T_true[:3, 3]) < 0.05
    assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) > 3.5
    # the figures the stats add up: 6 readings (the first has nothing to compare), 3 disagreeing, 1 failure
    assert (chk.readings, chk.disagreeing, chk.confirmed) == (6, 3, 1)
    assert chk.worst in chk.streak and chk.widest in chk.streak and chk.widest.gap_m_s > 3.0
    return chk


def test_the_flight_tally_adds_up_every_run_of_the_check():
    """A reset starts a new MotionCheck; the replay's stats add each run's to what the earlier ones read: counts
    summed, the largest reading in sigma and in m/s kept whichever run had it."""
    calib = synthetic_calibration()
    runaway = _runaway()
    quiet = MotionCheck(calib.cam0.K, calib.baseline_m, n_sigma=5.0, min_m_s=1.0, scale_sigma=0.1, confirm=3)
    mot, scene, rng = Motion(speed=1.0, still_s=0.0, seed=5), SyntheticScene(calib, seed=5), np.random.default_rng(5)
    for k in range(4):
        t = 1.0 + 0.3 * k
        assert quiet.add(int(t * 1e9), scene.observe(int(t * 1e9), mot.pose(t), pixel_sigma=0.5, rng=rng),
                         mot.pose(t) @ calib.cam0.T_body_cam) is None
    t = quiet.tally(runaway.tally(MotionTally()))
    assert (t.readings, t.disagreeing, t.resets) == (9, 3, 1)
    assert t.worst is runaway.worst and t.widest is runaway.widest
    other = runaway.tally(quiet.tally(MotionTally()))  # the order of the runs does not matter
    assert (other.readings, other.disagreeing, other.resets, other.worst, other.widest) == \
        (t.readings, t.disagreeing, t.resets, t.worst, t.widest)
    assert quiet.tally(MotionTally()).worst is quiet.worst and quiet.worst.n_sigma < 5.0


def test_one_bad_keyframe_in_a_streak_does_not_confirm_and_an_agreeing_one_ends_it():
    """A disagreement that comes and goes (one keyframe's pose jumps 1.2 m and back): two disagreeing readings (the
    jump and its return), then agreement: no failure, the streak ended; without stereo points there is no reading."""
    calib = synthetic_calibration()
    mot, scene, rng = Motion(speed=1.0, still_s=0.0, seed=4), SyntheticScene(calib, seed=4), np.random.default_rng(4)
    chk = MotionCheck(calib.cam0.K, calib.baseline_m, n_sigma=5.0, min_m_s=1.0, scale_sigma=0.1, confirm=3)
    for k in range(6):
        t = 1.0 + 0.3 * k
        T = mot.pose(t) @ calib.cam0.T_body_cam
        if k == 3:
            T[:3, 3] += [0.0, 1.2, 0.0]
        ff = scene.observe(int(t * 1e9), mot.pose(t), pixel_sigma=0.5, rng=rng)
        assert chk.add(int(t * 1e9), ff, T) is None
        assert len(chk.streak) == (k - 2 if k in (3, 4) else 0), k
    readings = chk.readings
    ff.depth_m[:] = np.nan
    assert chk.add(int(3.0e9), ff, T) is None and chk.readings == readings
