"""An identification run's phases (sim/excitation_run.py): the extended first settle phase, the
level search's probes, the plan from where the search ended, the end; without ROS."""
import numpy as np
from spring_finger import RATE, REST, SpringDamper

from soft_gripper_sdre.sim.excitation import ExcitationPlan, LevelSearch, LevelSettings
from soft_gripper_sdre.sim.excitation_run import ExcitationRun, Phase
from soft_gripper_sdre.sim.settle import SettlePhase
from soft_gripper_sdre.sim.signal_specs import builtin_signal

TIPS = REST[None, :]


def plan(duration: float = 1.0) -> ExcitationPlan:
    return ExcitationPlan([builtin_signal('u1', duration)], 0.5, 1)


def test_a_settle_phase_short_of_tips_is_extended_then_the_plan_plays_shifted_to_its_end():
    run = ExcitationRun(plan(), SettlePhase(0.5, 3))
    run.settle.heard_tips()
    first = run.at(0.4, TIPS)
    assert first.phase is Phase.PLAY and first.t == 0.4 and np.all(first.u == 0.0)
    settling = run.at(0.6, TIPS)                        # 1 of 3 tips heard at settle_time
    assert settling.phase is Phase.SETTLE and settling.t is None and np.all(settling.u == 0.0)
    run.settle.heard_tips()
    run.settle.heard_tips()
    step = run.at(0.7, TIPS)                            # the phase ends 0.2 s late
    assert step.phase is Phase.PLAY and abs(step.t - 0.5) < 1e-12
    assert step.first_torque is False and run.settle.zero_answers == 3    # u1 is 0 at its start
    step = run.at(0.8, TIPS)
    np.testing.assert_array_equal(step.u, run.plan.torques(step.t))
    assert step.first_torque and not run.at(0.9, TIPS).first_torque
    over = run.at(1.8, TIPS)
    assert over.phase is Phase.OVER and over.u is None and abs(over.t - 1.6) < 1e-12


def test_the_plan_starts_where_the_search_ended_scaled_to_the_chosen_amplitude():
    p = plan(2.0)
    search = LevelSearch(p.peak_torque, p.torque_limit, 0.02, 1,
                         settings=LevelSettings(probe_time=1.0, settle_time=0.5))
    run, finger = ExcitationRun(p, SettlePhase(0.5, 0), search), SpringDamper()
    k, step = 0, run.at(0.0, finger.tips())
    while step.phase is Phase.PROBE:
        finger.step(step.u[0])
        k += 1
        step = run.at(k / RATE, finger.tips())
    assert step.level_chosen and search.done and run.plan_offset == search.end
    assert run.plan.amplitude == search.amplitude
    assert step.phase is Phase.PLAY and abs(step.t - (k / RATE - search.end)) < 1e-12
    assert not run.at((k + 1) / RATE, finger.tips()).level_chosen


def test_the_excursion_is_the_excited_tips_distance_from_the_start():
    two = ExcitationPlan([builtin_signal('u1')], 0.5, 2, finger=1)
    run = ExcitationRun(two, SettlePhase(0.5, 0))
    start = np.array([REST, REST + [0.01, 0.0, 0.0]])
    run.start(start)
    moved = start + [[0.005, 0.0, 0.0], [0.0, 0.002, 0.0]]
    assert abs(run.excursion(moved) - 0.002) < 1e-12             # finger 0 is not excited
    moved[1, 0] = np.nan
    assert run.excursion(moved) == np.inf
