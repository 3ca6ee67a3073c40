"""The controller's loop rules (control/command_gate.py) driven by plain calls: stamps, arrays and
wall times, no DDS."""
import numpy as np
import pytest

from soft_gripper_sdre.control.command_gate import Answer, Change, CommandGate, Notice, STORED_HORIZONS
from soft_gripper_sdre.control.horizon import sample_horizon

MS = 1_000_000
N = 4
STEP_NS = 5 * MS               # grid of the horizons' points


def make_gate(timeout_ns=2 * MS, jump_ns=100 * MS, clock_timeout=1.0) -> CommandGate:
    return CommandGate(timeout_ns, jump_ns, clock_timeout)


def horizon(start_ns, points=21):
    """(stamp, times, pos, vel, acc) of a horizon on the absolute grid from ``start_ns``, sampling
    one smooth reference, so two horizons hold identical points where they overlap."""
    times = start_ns + STEP_NS * np.arange(points, dtype=np.int64)
    t = times[:, None, None] / 1e9
    finger = np.arange(N)[None, :, None] * 1e-3
    pos = np.concatenate([np.sin(t + finger), np.cos(2 * t + finger)], axis=2) * 1e-2
    vel = np.concatenate([np.cos(t + finger), -2 * np.sin(2 * t + finger)], axis=2) * 1e-2
    acc = np.concatenate([-np.sin(t + finger), -4 * np.cos(2 * t + finger)], axis=2) * 1e-2
    return int(times[0]), times, pos, vel, acc


def estimate(value=0.0):
    return np.full((N, 4), value)


def test_an_estimate_is_answered_with_the_horizon_that_covers_its_stamp():
    gate = make_gate()
    ref = horizon(0)
    assert gate.on_reference(*ref).answer is None
    x = estimate(1.0)
    out = gate.on_estimate(3 * MS, x, wall=0.0)
    assert out.answer.stamp == 3 * MS and out.answer.estimate is x and not out.answer.safe
    np.testing.assert_array_equal(out.answer.reference.times, ref[1])
    assert out.refused is None and out.notices == ()
    assert gate.counters == {'references': 1, 'estimates': 1}
    assert gate.last_command_ns == 3 * MS


def test_a_late_covering_reference_answers_the_waiting_estimate():
    gate = make_gate()
    x = estimate(2.0)
    out = gate.on_estimate(13 * MS, x, wall=0.0)
    assert out.answer is None and gate.pending[0] == 13 * MS      # nothing to track yet
    assert gate.on_reference(*horizon(0, points=2)).answer is None  # ends at 5 ms: still waits
    out = gate.on_reference(*horizon(10 * MS))
    assert out.answer.stamp == 13 * MS and out.answer.estimate is x
    assert out.answer.reference is gate.horizons[-1]
    assert gate.pending is None
    assert gate.on_reference(*horizon(10 * MS)).answer is None      # answered once only


def test_a_waiting_estimate_superseded_by_a_newer_one_is_counted_and_only_the_newer_answered():
    gate = make_gate()
    gate.on_estimate(3 * MS, estimate(), wall=0.0)
    gate.on_estimate(4 * MS, estimate(), wall=0.0)
    assert gate.counters['unanswered_estimates'] == 1
    out = gate.on_reference(*horizon(0))
    assert out.answer.stamp == 4 * MS


def test_the_newest_covering_horizon_is_used_and_only_a_few_are_kept():
    gate = make_gate()
    for k in range(STORED_HORIZONS + 2):
        gate.on_reference(*horizon(k * 20 * MS))
    assert len(gate.horizons) == STORED_HORIZONS
    assert gate.covering(0) is None                                 # the oldest were dropped
    assert gate.covering(100 * MS).start == 100 * MS                # covered by four: the newest
    assert gate.covering(50 * MS).start == 40 * MS


@pytest.mark.parametrize('seed', range(5))
def test_the_answers_do_not_depend_on_which_message_arrives_first(seed):
    """Each horizon arrives just before or just after the estimate of its own instant: every
    estimate is answered, with the same stamp and the same sampled reference."""
    rng = np.random.default_rng(seed)

    def run(reference_first):
        gate = make_gate()
        sampled = []
        for k in range(100):
            stamp = k * MS
            outs = []
            events = [('est', stamp)]
            if k % 20 == 0:
                events.insert(0 if reference_first[k // 20] else 1, ('ref', stamp))
            for kind, t in events:
                outs.append(gate.on_reference(*horizon(t, points=9)) if kind == 'ref'
                            else gate.on_estimate(t, estimate(k), wall=0.0))
            for out in outs:
                if out.answer is not None:
                    a = out.answer
                    r = a.reference
                    sampled.append((a.stamp, *sample_horizon(r.times, r.pos, r.vel, r.acc, a.stamp,
                                                             with_acc=True)))
        return sampled

    in_order = run([True] * 5)
    shuffled = run(list(rng.random(5) < 0.5))
    assert [s[0] for s in in_order] == [k * MS for k in range(100)]
    assert len(shuffled) == len(in_order)
    for a, b in zip(in_order, shuffled):
        assert a[0] == b[0]
        for u, v in zip(a[1:], b[1:]):
            np.testing.assert_array_equal(u, v)


def test_old_messages_are_refused_not_counted_and_change_nothing():
    gate = make_gate()
    gate.on_reference(*horizon(20 * MS))
    out = gate.on_reference(*horizon(15 * MS))
    assert out.refused == 'old_reference' and '15000000' in out.reason and out.answer is None
    assert gate.on_reference(*horizon(20 * MS)).refused is None      # the same stamp again is kept
    gate.on_estimate(30 * MS, estimate(), wall=0.0)
    for stamp in (30 * MS, 29 * MS):                                 # not newer
        out = gate.on_estimate(stamp, estimate(), wall=0.0)
        assert out.refused == 'old_estimate' and out.answer is None
    assert gate.counters['estimates'] == 1 and gate.counters['references'] == 2
    assert 'old_estimate' not in gate.counters                      # the caller counts refusals


def test_lost_estimates_get_the_safe_command_stamped_with_the_tick_then_tracking_resumes():
    gate = make_gate(timeout_ns=2 * MS)
    gate.on_reference(*horizon(0, points=200))
    assert gate.on_tick(1 * MS, wall=0.0).answer is None
    assert gate.on_estimate(1 * MS, estimate(), wall=0.0).answer.stamp == 1 * MS
    assert gate.on_tick(2 * MS, wall=0.0).answer is None             # one period behind: waits
    out = gate.on_tick(3 * MS, wall=0.0)                             # two periods: safe command
    assert out.answer == Answer(3 * MS) and out.answer.safe
    assert out.notices == (Notice(Change.ESTIMATES_LOST, 1 * MS),)
    assert gate.estimates_lost
    for k in (4, 5):
        out = gate.on_tick(k * MS, wall=0.0)
        assert out.answer == Answer(k * MS) and out.notices == ()  # reported once
    assert gate.counters['safe_commands'] == 3
    out = gate.on_estimate(5 * MS, estimate(), wall=0.0)            # its instant got zero: skipped
    assert out.answer is None and out.notices == (Notice(Change.ESTIMATES_BACK, 5 * MS),)
    assert gate.counters['late_estimates'] == 1 and not gate.estimates_lost
    assert gate.on_tick(6 * MS, wall=0.0).answer is None
    assert gate.on_estimate(6 * MS, estimate(), wall=0.0).answer.stamp == 6 * MS


def test_an_estimate_arrives_at_the_newer_of_its_stamp_and_the_tick():
    """An estimator behind sim time is not lost: its estimate counts as arriving at the tick."""
    gate = make_gate(timeout_ns=2 * MS)
    gate.on_tick(10 * MS, wall=0.0)
    gate.on_estimate(7 * MS, estimate(), wall=0.0)
    assert gate.estimate_arrived_ns == 10 * MS
    assert gate.on_tick(11 * MS, wall=0.0).answer is None
    assert gate.on_tick(12 * MS, wall=0.0).answer == Answer(12 * MS)


def test_no_safe_command_before_the_first_estimate_nor_for_an_answered_instant():
    gate = make_gate(timeout_ns=2 * MS)
    for k in range(10):
        assert gate.on_tick(k * MS, wall=0.0).answer is None
    gate.on_reference(*horizon(0, points=200))
    gate.on_estimate(20 * MS, estimate(), wall=0.0)                   # answered at 20 ms
    assert gate.on_tick(20 * MS, wall=0.0).answer is None
    assert gate.on_tick(25 * MS, wall=0.0).answer == Answer(25 * MS)
    assert gate.on_tick(25 * MS, wall=0.0).answer is None             # already answered


def test_the_safe_command_supersedes_a_waiting_estimate():
    gate = make_gate(timeout_ns=2 * MS)
    gate.on_estimate(1 * MS, estimate(), wall=0.0)                    # waits: no horizon
    assert gate.on_tick(3 * MS, wall=0.0).answer == Answer(3 * MS)
    assert gate.pending is None
    assert gate.on_reference(*horizon(0)).answer is None


def test_the_timeout_can_change_between_calls():
    gate = make_gate(timeout_ns=2 * MS)
    gate.on_estimate(1 * MS, estimate(), wall=0.0)
    gate.estimate_timeout_ns = 5 * MS
    assert gate.on_tick(3 * MS, wall=0.0).answer is None
    assert gate.on_tick(6 * MS, wall=0.0).answer == Answer(6 * MS)


@pytest.mark.parametrize('kind', ['reference', 'estimate', 'tick'])
def test_time_jumping_back_resets_and_a_small_step_back_is_refused(kind):
    gate = make_gate(jump_ns=100 * MS)
    late = 2000 * MS
    gate.on_reference(*horizon(late))
    gate.on_tick(late, wall=0.0)
    assert gate.on_estimate(late, estimate(), wall=0.0).answer.stamp == late
    feed = {'reference': lambda t: gate.on_reference(*horizon(t)),
            'estimate': lambda t: gate.on_estimate(t, estimate(), wall=0.0),
            'tick': lambda t: gate.on_tick(t, wall=0.0)}[kind]
    out = feed(late - 50 * MS)                                         # within reset_jump: old
    assert out.notices == () and gate.counters['resets'] == 0
    if kind != 'tick':                                                 # a tick never is refused
        assert out.refused == f'old_{kind}'
    out = feed(0)                                                      # 2 s back: a restart
    assert out.notices[0] == Notice(Change.RESET, 0) and out.refused is None
    assert gate.counters['resets'] == 1 and gate.last_command_ns == -1
    assert len(gate.horizons) == (1 if kind == 'reference' else 0)
    # the new run is tracked from t = 0
    if kind == 'estimate':                         # the estimate after the jump waits for a horizon
        assert gate.pending[0] == 0
        answer = gate.on_reference(*horizon(0)).answer
    else:
        assert gate.pending is None and gate.estimate_arrived_ns == -1
        if kind == 'tick':
            gate.on_reference(*horizon(0))
        answer = gate.on_estimate(0, estimate(), wall=0.0).answer
    assert answer.stamp == 0


def test_wall_watchdog_answers_the_open_instant_once_when_time_stops():
    gate = make_gate(clock_timeout=1.0)
    assert gate.on_wall_time(100.0).notices == ()                       # nothing heard yet: idle
    gate.on_estimate(4 * MS, estimate(), wall=10.0)                    # no horizon: unanswered
    assert gate.on_wall_time(10.5).answer is None
    out = gate.on_wall_time(11.0)
    assert out.notices == (Notice(Change.TIME_STOPPED, 4 * MS),)
    assert out.answer == Answer(4 * MS) and gate.time_stopped
    assert gate.on_wall_time(12.0).answer is None                      # nothing newer to stamp
    assert gate.on_wall_time(13.0).notices == ()                       # reported once
    gate.on_reference(*horizon(0))
    out = gate.on_estimate(5 * MS, estimate(), wall=14.0)
    assert out.notices == (Notice(Change.TIME_MOVES, 5 * MS),) and out.answer.stamp == 5 * MS
    assert not gate.time_stopped and gate.on_wall_time(14.5).answer is None
    assert gate.counters['safe_commands'] == 1


def test_wall_watchdog_sends_nothing_for_an_answered_instant_and_a_tick_restarts_time():
    gate = make_gate(clock_timeout=1.0)
    gate.on_reference(*horizon(0))
    gate.on_estimate(4 * MS, estimate(), wall=0.0)                     # answered
    out = gate.on_wall_time(2.0)
    assert out.notices == (Notice(Change.TIME_STOPPED, 4 * MS),) and out.answer is None
    gate.clock_timeout = 5.0                                           # may change between calls
    out = gate.on_tick(5 * MS, wall=3.0)
    assert out.notices == (Notice(Change.TIME_MOVES, 5 * MS),)
    assert gate.on_wall_time(7.0).notices == ()
    assert gate.on_wall_time(8.0).notices == (Notice(Change.TIME_STOPPED, 5 * MS),)


def test_time_moving_again_is_not_reported_while_estimates_are_lost():
    gate = make_gate(timeout_ns=2 * MS, clock_timeout=1.0)
    gate.on_estimate(1 * MS, estimate(), wall=0.0)
    assert gate.on_tick(3 * MS, wall=0.0).notices[0].change is Change.ESTIMATES_LOST
    assert gate.on_wall_time(1.0).notices[0].change is Change.TIME_STOPPED
    out = gate.on_tick(4 * MS, wall=2.0)                               # time moves, estimates still lost
    assert out.notices == () and out.answer == Answer(4 * MS) and not gate.time_stopped
    out = gate.on_estimate(5 * MS, estimate(), wall=2.0)
    assert out.notices == (Notice(Change.ESTIMATES_BACK, 5 * MS),)
