"""The first settle phase's rules (sim/settle.py) on run times and torques, without DDS."""
import numpy as np

from soft_gripper_sdre.sim.settle import SettlePhase

ZERO, TORQUE = np.zeros((2, 2)), np.array([[0.0, 0.01], [0.0, 0.0]])


def test_a_phase_whose_samples_arrive_in_time_shifts_nothing():
    s = SettlePhase(0.5, 3)
    for t in (0.0, 0.2, 0.4):
        assert s.run_time(t) == t
        s.heard_tips()
    assert s.run_time(0.6) == 0.6 and s.shift == 0.0 and not s.extended


def test_too_few_samples_extend_the_phase_and_shift_every_later_time():
    s = SettlePhase(0.5, 3)
    s.heard_tips()
    assert s.run_time(0.5) is None and s.extended        # 1 of 3 heard at settle_time
    s.heard_tips()
    assert s.run_time(0.6) is None
    s.heard_tips()
    assert s.run_time(0.7) == 0.5 and abs(s.shift - 0.2) < 1e-12
    s.heard_tips()                                      # heard after the phase: not counted
    assert s.heard == 3 and abs(s.run_time(1.0) - 0.8) < 1e-12


def test_no_settle_time_means_no_phase_whatever_the_samples():
    s = SettlePhase(0.0, 100)
    assert s.run_time(0.0) == 0.0 and s.shift == 0.0 and not s.extended


def test_zero_answers_are_counted_until_the_first_torque_which_is_reported_once():
    s = SettlePhase(0.5, 3)
    assert [s.answered(ZERO) for _ in range(4)] == [False] * 4
    assert s.answered(TORQUE) and s.excited and s.zero_answers == 4
    assert not s.answered(ZERO) and not s.answered(TORQUE) and s.zero_answers == 4
