"""The controller's loop rules (control/command_gate.py) driven by plain calls: stamps, arrays and
wall times, no DDS."""
import numpy as np
import pytest

from soft_gripper_sdre.control.command_gate import Change, CommandGate, Notice
from soft_gripper_sdre.control.horizon import sample_plan

MS = 1_000_000
N = 4
STEP_NS = 5 * MS               # grid of the plan's points


def make_gate(jump_ns=100 * MS, watchdog=1.0) -> CommandGate:
    return CommandGate(MS, jump_ns, watchdog)


def plan(start_ns=0, points=21, offset=0.0):
    """(times, pos, vel, acc) of a plan on the absolute grid from ``start_ns``, sampling one smooth
    reference (shifted by ``offset``)."""
    times = start_ns + STEP_NS * np.arange(points, dtype=np.int64)
    t = times[:, None, None] / 1e9
    finger = np.arange(N)[None, :, None] * 1e-3
    pos = np.concatenate([np.sin(t + finger), np.cos(2 * t + finger)], axis=2) * 1e-2 + offset
    vel = np.concatenate([np.cos(t + finger), -2 * np.sin(2 * t + finger)], axis=2) * 1e-2
    acc = np.concatenate([-np.sin(t + finger), -4 * np.cos(2 * t + finger)], axis=2) * 1e-2
    return times, pos, vel, acc


def estimate(value=0.0):
    return np.full((N, 4), value)


def test_an_estimate_is_answered_with_the_plan_that_covers_its_stamp():
    gate = make_gate()
    ref = plan()
    assert gate.on_plan(*ref).answer is None
    x = estimate(1.0)
    out = gate.on_estimate(3 * MS, x, wall=0.0)
    assert out.answer.stamp == 3 * MS and out.answer.estimate is x
    np.testing.assert_array_equal(out.answer.plan.times, ref[0])
    assert out.refused is None and out.notices == ()
    assert gate.counters == {'references': 1, 'estimates': 1}


def test_a_plan_covers_everything_after_its_start_and_an_earlier_estimate_waits():
    gate = make_gate()
    gate.on_plan(*plan(start_ns=10 * MS, points=3))                 # 10 … 20 ms
    assert gate.on_estimate(5 * MS, estimate(), wall=0.0).answer is None   # before its start
    assert gate.on_estimate(10 * MS, estimate(), wall=0.0).answer.stamp == 10 * MS
    assert gate.on_estimate(10_000 * MS, estimate(), wall=0.0).answer.stamp == 10_000 * MS  # held
    assert gate.counters['unanswered_estimates'] == 0 and gate.pending is None


def test_a_late_plan_answers_the_waiting_estimate():
    gate = make_gate()
    x = estimate(2.0)
    out = gate.on_estimate(13 * MS, x, wall=0.0)
    assert out.answer is None and gate.pending[0] == 13 * MS      # nothing to track yet
    assert gate.on_plan(*plan(start_ns=15 * MS)).answer is None   # starts after it: still waits
    out = gate.on_plan(*plan())
    assert out.answer.stamp == 13 * MS and out.answer.estimate is x
    assert out.answer.plan is gate.plan and gate.pending is None
    assert gate.on_plan(*plan()).answer is None                   # answered once only


def test_a_waiting_estimate_superseded_by_a_newer_one_is_counted_and_only_the_newer_answered():
    gate = make_gate()
    gate.on_estimate(3 * MS, estimate(), wall=0.0)
    gate.on_estimate(4 * MS, estimate(), wall=0.0)
    assert gate.counters['unanswered_estimates'] == 1
    assert gate.on_plan(*plan()).answer.stamp == 4 * MS


def test_a_new_plan_replaces_the_old_one():
    gate = make_gate()
    gate.on_plan(*plan())
    gate.on_plan(*plan(offset=1.0))
    answer = gate.on_estimate(1 * MS, estimate(), wall=0.0).answer
    assert answer.plan.pos[0, 0, 0] > 0.5 and gate.counters['references'] == 2


@pytest.mark.parametrize('plan_first', [True, False])
def test_the_answers_do_not_depend_on_whether_the_plan_or_the_first_estimate_arrives_first(
        plan_first):
    """Lockstep has one estimate in flight: the plan comes just before or just after the first."""
    def run(plan_first):
        gate = make_gate()
        sampled = []
        for k in range(50):
            events = [('est', k * MS)]
            if k == 0:
                events.insert(0 if plan_first else 1, ('plan', 0))
            for kind, t in events:
                out = (gate.on_plan(*plan(points=200)) if kind == 'plan'
                       else gate.on_estimate(t, estimate(k), wall=0.0))
                if out.answer is not None:
                    a, p = out.answer, out.answer.plan
                    sampled.append((a.stamp, *sample_plan(p.times, p.pos, p.vel, p.acc, a.stamp,
                                                          with_acc=True)))
        return sampled

    got, reference = run(plan_first), run(True)
    assert [s[0] for s in got] == [k * MS for k in range(50)]
    for a, b in zip(got, reference):
        for u, v in zip(a[1:], b[1:]):
            np.testing.assert_array_equal(u, v)


def test_old_estimates_are_refused_and_gaps_are_counted_as_skipped():
    gate = make_gate()
    gate.on_plan(*plan())
    gate.on_estimate(30 * MS, estimate(), wall=0.0)
    for stamp in (30 * MS, 29 * MS):                                 # not newer
        out = gate.on_estimate(stamp, estimate(), wall=0.0)
        assert out.refused == 'old_estimate' and out.answer is None and str(stamp) in out.reason
    assert 'old_estimate' not in gate.counters                      # the caller counts refusals
    gate.on_estimate(34 * MS, estimate(), wall=0.0)                 # 31, 32, 33 never came
    gate.on_estimate(35 * MS, estimate(), wall=0.0)
    assert gate.counters['skipped_estimates'] == 3 and gate.counters['estimates'] == 3
    gate.on_estimate(10_000 * MS, estimate(), wall=0.0)             # an outage, not a skip
    assert gate.counters['skipped_estimates'] == 3
    gate.on_estimate(10_001 * MS + MS // 3, estimate(), wall=0.0)   # a jittery step: none skipped
    gate.on_estimate(10_003 * MS + MS // 4, estimate(), wall=0.0)   # about two periods: one skipped
    assert gate.counters['skipped_estimates'] == 4


def test_the_watchdog_reports_lost_estimates_once_and_their_return():
    gate = make_gate(watchdog=0.5)
    assert gate.on_wall_time(100.0).notices == () and not gate.estimates_lost   # nothing heard yet
    gate.on_plan(*plan())
    gate.on_estimate(4 * MS, estimate(), wall=10.0)
    assert gate.on_wall_time(10.49).notices == ()
    out = gate.on_wall_time(10.5)
    assert out.notices == (Notice(Change.ESTIMATES_LOST, 4 * MS),) and out.answer is None
    assert gate.on_wall_time(11.0).notices == ()                     # reported once
    out = gate.on_estimate(5 * MS, estimate(), wall=12.0)
    assert out.notices == (Notice(Change.ESTIMATES_BACK, 5 * MS),) and out.answer.stamp == 5 * MS
    gate.watchdog = 5.0                                              # may change between calls
    assert gate.on_wall_time(13.0).notices == ()


def test_estimates_that_stop_past_the_plans_end_are_the_run_ending_not_a_loss():
    gate = make_gate(watchdog=0.5)
    times = plan()[0]
    gate.on_plan(*plan())
    gate.on_estimate(int(times[-1]) - MS, estimate(), wall=10.0)      # one period before the end
    assert gate.on_wall_time(10.5).notices == (Notice(Change.ESTIMATES_LOST,
                                                      int(times[-1]) - MS),)
    gate.on_estimate(int(times[-1]), estimate(), wall=11.0)           # at the end: back
    out = gate.on_wall_time(11.5)
    assert out.notices == (Notice(Change.RUN_ENDED, int(times[-1])),) and out.answer is None
    assert gate.on_wall_time(12.0).notices == ()                      # reported once
    out = gate.on_estimate(int(times[-1]) + MS, estimate(), wall=12.5)  # a run that goes on
    assert out.notices == (Notice(Change.ESTIMATES_BACK, int(times[-1]) + MS),)
    # judged against the plan in force when the last estimate came, not one that came after it
    gate.on_plan(*plan(points=3))                                     # a shorter plan arrives
    gate.on_estimate(int(times[-1]) + 2 * MS, estimate(), wall=13.0)  # past its end too
    gate.on_plan(*plan(points=5000))                                  # then a much longer one
    assert gate.on_wall_time(13.5).notices == (Notice(Change.RUN_ENDED,
                                                      int(times[-1]) + 2 * MS),)


def test_time_jumping_back_resets_and_the_old_runs_plan_is_forgotten():
    gate = make_gate(jump_ns=100 * MS)
    gate.on_plan(*plan())
    for k in range(2000, 2005):
        gate.on_estimate(k * MS, estimate(), wall=0.0)
    out = gate.on_estimate(1950 * MS, estimate(), wall=0.0)          # within reset_jump: old
    assert out.refused == 'old_estimate' and gate.counters['resets'] == 0
    out = gate.on_estimate(0, estimate(), wall=0.0)                  # 2 s back: a restart
    assert out.notices == (Notice(Change.RESET, 0),) and out.refused is None and out.answer is None
    assert gate.counters['resets'] == 1 and gate.plan is None and gate.pending[0] == 0
    out = gate.on_plan(*plan(offset=1.0))                            # the new run's plan
    assert out.answer.stamp == 0 and out.answer.plan.pos[0, 0, 0] > 0.5


def test_a_new_runs_plan_that_beats_the_new_runs_first_estimate_is_kept():
    gate = make_gate(jump_ns=100 * MS)
    gate.on_plan(*plan())
    gate.on_estimate(2000 * MS, estimate(), wall=0.0)
    gate.on_plan(*plan(offset=1.0))                                  # the restart's plan, early
    gate.on_estimate(2001 * MS, estimate(), wall=0.0)                # an old run's estimate in
                                                                     # flight
    out = gate.on_estimate(0, estimate(), wall=0.0)
    assert out.notices[0].change is Change.RESET
    assert out.answer.stamp == 0 and out.answer.plan.pos[0, 0, 0] > 0.5
