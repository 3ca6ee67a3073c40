"""The simulator's stepping rules (sim/lockstep.py) driven by plain calls: stamps, torques and
wall times, no DDS and no physics."""
import numpy as np
import pytest

from soft_gripper_sdre.sim.lockstep import LATENCY_PERIODS, Stepping

MS = 1_000_000
N = 2


def torque(value):
    return np.full((N, 2), float(value))


def started(**kwargs) -> Stepping:
    stepping = Stepping(N, MS, **kwargs)
    stepping.start()
    stepping.await_command(0.0)
    return stepping


def overdue(s: Stepping, wall: float):
    """The watchdog's two looks past the deadline: the first never steps, the second's result."""
    assert s.on_wall_time(wall) is None
    return s.on_wall_time(wall)


def test_lockstep_steps_once_per_command_of_the_current_period():
    s = started()
    for k in range(3):
        u = torque(k + 1)
        out = s.on_command(k * MS, u)
        assert out.step is u and out.refused is None and out.first_answer == k
        assert s.k == k + 1 and s.now_ns == (k + 1) * MS
    np.testing.assert_array_equal(s.held, torque(3))
    assert s.counters == {'commands': 3, 'steps': 3}


def test_nothing_steps_before_the_start():
    s = Stepping(N, MS)
    out = s.on_command(0, torque(1))
    assert out.step is None and out.first_answer is None and s.k == 0
    assert s.counters['late_command'] == 1
    assert s.on_wall_time(1e9) is None                     # no timeout before the first tips


@pytest.mark.parametrize('stamp, key', [(0, 'stale_command'), (1 * MS, 'stale_command'),
                                        (3 * MS, 'future_command'), (2 * MS + 1, 'future_command')])
def test_duplicate_old_and_future_stamps_are_refused(stamp, key):
    s = started()
    s.on_command(0, torque(1))
    s.on_command(1 * MS, torque(2))                        # now at period 2
    out = s.on_command(stamp, torque(9))
    assert out.refused == key and out.step is None and str(stamp) in out.reason
    assert s.k == 2 and key not in s.counters             # the caller counts refusals
    np.testing.assert_array_equal(s.held, torque(2))       # on_bad_command='hold'


@pytest.mark.parametrize('u', [np.zeros((N + 1, 2)), np.zeros(2 * N),
                               np.array([[np.nan, 0.0], [0.0, 0.0]]),
                               np.array([[0.0, np.inf], [0.0, 0.0]])])
def test_wrong_size_or_non_finite_torques_are_refused(u):
    s = started()
    out = s.on_command(0, u)
    assert out.refused == 'bad_command' and out.step is None and s.k == 0
    assert out.first_answer is None


def test_a_refused_command_drops_the_held_one_with_the_zero_policy():
    s = started(on_bad_command='zero')
    s.on_command(0, torque(1))
    assert s.on_command(5 * MS, torque(2)).refused == 'future_command'
    np.testing.assert_array_equal(s.held, 0.0)
    s.on_command(1 * MS, torque(3))
    s.command_refused()                                    # a message the node could not decode
    np.testing.assert_array_equal(s.held, 0.0)


@pytest.mark.parametrize('policy, expected', [('hold', 4.0), ('zero', 0.0)])
def test_lockstep_timeout_steps_with_the_held_or_zero_command_and_counts(policy, expected):
    s = started(timeout=0.5, on_timeout=policy)
    s.on_command(0, torque(4))
    s.await_command(10.0)                                 # tips of period 1 went out at 10 s
    assert s.on_wall_time(10.49) is None
    u = overdue(s, 10.5)
    np.testing.assert_array_equal(u, expected)
    assert s.k == 2 and s.counters['timeouts'] == 1 and s.counters['steps'] == 2
    # the missed period's command arrives after all: counted, not applied
    out = s.on_command(1 * MS, torque(5))
    assert out.step is None and out.refused is None and s.counters['late_command'] == 1
    # and the current one steps as usual
    s.await_command(11.0)
    assert s.on_command(2 * MS, torque(6)).step is not None and s.k == 3


def test_a_command_waiting_behind_the_first_late_look_steps_its_period_not_a_timeout():
    """A starved simulator wakes with its watchdog and the command both due and may run the
    watchdog first. Its first look past the deadline waits, the command is taken, no timeout."""
    s = started(timeout=0.05)
    s.on_command(0, torque(4))
    s.await_command(10.0)
    assert s.on_wall_time(10.3) is None                   # long past the deadline: the first look
    out = s.on_command(1 * MS, torque(5))
    assert out.step is not None and s.k == 2 and 'timeouts' not in s.counters and not s.lost
    s.await_command(10.3)                                 # the next period gets its own two looks
    assert s.on_wall_time(10.36) is None
    np.testing.assert_array_equal(s.on_wall_time(10.37), torque(5))
    assert s.counters['timeouts'] == 1


def test_after_a_timeout_lost_commands_step_with_zero_after_a_short_wait_until_one_arrives():
    s = started(timeout=0.5, lost_command_wait=0.01)
    s.on_command(0, torque(4))
    s.await_command(10.0)                                 # period 1: awaited until 10.5 s
    np.testing.assert_array_equal(overdue(s, 10.5), torque(4))        # the timeout holds
    assert s.lost and s.lost_since_ns == 1 * MS and s.counters['timeouts'] == 1
    s.await_command(10.5)                                 # period 2: awaited 0.01 s only
    assert s.deadline == pytest.approx(10.51)
    assert s.on_wall_time(10.505) is None
    np.testing.assert_array_equal(overdue(s, 10.51), 0.0)
    s.await_command(10.51)
    np.testing.assert_array_equal(overdue(s, 10.52), 0.0)
    assert s.counters['safe_periods'] == 2 and s.counters['timeouts'] == 1 and s.k == 4
    s.await_command(10.52)
    out = s.on_command(4 * MS, torque(5))                 # commands are back: tracking
    assert out.resumed and out.step is not None and not s.lost and s.k == 5
    s.await_command(10.53)
    assert s.deadline == pytest.approx(11.03)            # the full timeout again


def test_before_the_loop_ever_answered_every_period_waits_the_full_timeout():
    """At start-up the controller may still be waiting for its plan: nothing is lost yet."""
    s = started(timeout=0.5, lost_command_wait=0.01)
    for k in range(3):
        s.await_command(10.0 + k)
        assert s.on_wall_time(10.49 + k) is None
        np.testing.assert_array_equal(overdue(s, 10.5 + k), 0.0)
    assert s.counters['timeouts'] == 3 and not s.lost and 'safe_periods' not in s.counters


def test_a_late_command_while_lost_ends_the_short_wait_the_loop_is_slow_not_dead():
    s = started(timeout=0.5, lost_command_wait=0.01)
    s.on_command(0, torque(4))
    s.await_command(10.0)
    overdue(s, 10.5)                                      # timeout: period 1 held
    s.await_command(10.5)
    overdue(s, 10.51)                                     # period 2 zero
    s.await_command(10.51)
    out = s.on_command(2 * MS, torque(5))                 # period 2's answer, after all
    assert out.step is None and out.resumed and s.counters['late_command'] == 1
    assert s.deadline == pytest.approx(11.01)             # period 3 waits the full timeout
    assert s.on_wall_time(10.6) is None


def test_a_deadline_that_moves_within_a_period_gets_its_own_two_looks():
    s = started(timeout=0.5, lost_command_wait=0.01)
    s.on_command(0, torque(4))
    s.await_command(10.0)
    overdue(s, 10.5)                                      # timeout: period 1 held, commands lost
    s.await_command(10.5)
    assert s.on_wall_time(10.52) is None                  # period 2: first look past 10.51
    s.on_command(1 * MS, torque(5))                       # a late answer: the loop is slow, not
                                                          # dead
    assert not s.lost and s.deadline == pytest.approx(11.0)
    assert s.on_wall_time(11.0) is None and s.k == 2      # the new deadline's first look
    np.testing.assert_array_equal(s.on_wall_time(11.0), torque(4))
    assert s.counters['timeouts'] == 2 and 'safe_periods' not in s.counters


def test_refused_commands_do_not_end_lost_commands():
    s = started(timeout=0.5, lost_command_wait=0.01)
    s.on_command(0, torque(4))
    s.await_command(10.0)
    overdue(s, 10.5)
    assert s.on_command(0, torque(1)).refused == 'stale_command'
    assert s.on_command(9 * MS, torque(1)).refused == 'future_command'
    assert s.lost


def test_timeout_policy_and_length_can_change_between_calls():
    s = started(timeout=0.5, on_timeout='hold')
    s.on_command(0, torque(4))
    s.timeout, s.on_timeout = 2.0, 'zero'
    s.await_command(10.0)
    assert s.on_wall_time(11.0) is None
    np.testing.assert_array_equal(overdue(s, 12.0), 0.0)


def test_the_run_stops_after_total_steps():
    s = started(total_steps=2)
    s.on_command(0, torque(1))
    assert not s.done
    s.await_command(0.0)
    assert overdue(s, 1.0) is not None and s.done and s.k == 2
    out = s.on_command(2 * MS, torque(1))
    assert out.step is None and s.counters['late_command'] == 1
    s.await_command(2.0)
    assert s.on_wall_time(100.0) is None and s.k == 2


def test_realtime_steps_each_period_with_the_newest_command_and_counts_late_periods():
    s = started(mode='realtime')
    np.testing.assert_array_equal(s.on_period(), 0.0)       # nothing yet: zero, late
    assert s.counters['late_periods'] == 1 and s.k == 1
    out = s.on_command(1 * MS, torque(1))
    assert out.step is None and out.refused is None           # applied by the next period
    np.testing.assert_array_equal(s.on_period(), torque(1))   # period 1: its own command
    np.testing.assert_array_equal(s.on_period(), torque(1))   # period 2: one period of transport
                                                              # delay
    assert s.counters['late_periods'] == 1
    np.testing.assert_array_equal(s.on_period(), torque(1))   # period 3: held, and late
    assert s.counters['late_periods'] == 2 and s.k == 4
    s.on_command(2 * MS, torque(2))                           # newer, for a period long past:
    np.testing.assert_array_equal(s.on_period(), torque(2))   # applied, but period 4 is still late
    assert s.counters['late_periods'] == 3
    assert s.on_wall_time(1e9) is None and s.counters['timeouts'] == 0   # no lockstep timeout


def test_realtime_holds_a_late_command_for_hold_periods_then_steps_with_zero():
    s = started(mode='realtime', hold_periods=3)
    s.on_command(0, torque(1))
    for _ in range(4):                                        # periods 0, 1 on time, 2, 3 held
        np.testing.assert_array_equal(s.on_period(), torque(1))
        assert not s.lost
    assert s.counters['late_periods'] == 2 and s.counters['safe_periods'] == 0
    np.testing.assert_array_equal(s.on_period(), 0.0)         # period 4: the command is 4 old
    np.testing.assert_array_equal(s.on_period(), 0.0)
    assert s.lost and s.lost_since_ns == 1 * MS and s.counters['safe_periods'] == 2
    out = s.on_command(5 * MS, torque(2))                     # commands are back
    assert out.resumed and not s.lost
    np.testing.assert_array_equal(s.on_period(), torque(2))   # period 6: on time
    assert s.counters['late_periods'] == 4 and s.counters['safe_periods'] == 2
    s.hold_periods = 0                                        # may change between calls
    s.on_period()
    np.testing.assert_array_equal(s.on_period(), 0.0)         # period 8: 3 old


def test_realtime_zeroes_nothing_before_the_first_command():
    s = started(mode='realtime', hold_periods=1)
    for _ in range(5):
        np.testing.assert_array_equal(s.on_period(), 0.0)
    assert s.counters['late_periods'] == 5 and 'safe_periods' not in s.counters and not s.lost


def test_lockstep_has_no_periods_of_its_own():
    s = started()
    assert s.on_period() is None and s.k == 0


def test_the_loop_latency_counts_the_first_answer_of_each_period_only():
    s = started(mode='realtime')
    for _ in range(3):
        s.on_period()                                          # now at period 3
    assert s.on_command(2 * MS, torque(1)).first_answer == 2
    assert s.on_command(2 * MS, torque(1)).first_answer is None   # a duplicate
    assert s.on_command(1 * MS, torque(1)).first_answer is None   # older than an answered one
    assert s.on_command(3 * MS - 1, torque(1)).first_answer is None   # off the period grid
    assert s.on_command(3 * MS, torque(1)).first_answer == 3
    for _ in range(LATENCY_PERIODS + 2):
        s.on_period()
    assert s.on_command(5 * MS, torque(1)).first_answer is None   # too far back to time


def test_bad_modes_and_policies_are_refused():
    for kwargs in ({'mode': 'warp'}, {'on_timeout': 'explode'}, {'on_bad_command': 'maybe'}):
        with pytest.raises(ValueError, match=repr(next(iter(kwargs.values())))):
            Stepping(N, MS, **kwargs)
    with pytest.raises(ValueError, match="mode 'pipeline' must be one of .*'pipelined'"):
        Stepping(N, MS, mode='pipeline')


def _waiting_rules_trace(mode: str) -> list:
    """Every waiting rule of lockstep, driven by one script: what each call returned."""
    s = Stepping(N, MS, mode=mode, timeout=0.5, lost_command_wait=0.01, total_steps=7)
    trace = [s.on_command(0, torque(1)).step, s.on_wall_time(1e9)]     # before the start: nothing
    s.start()
    s.await_command(0.0)
    for k in range(2):                                   # periods 0, 1 answered on time
        trace.append(s.on_command(k * MS, torque(k + 1)).step)
        s.await_command(1.0 + k)
    trace += [s.on_command(1 * MS, torque(9)).refused, s.on_command(5 * MS, torque(9)).refused,
              s.on_command(2 * MS, torque(np.nan)).refused]
    trace += [s.on_wall_time(3.49), s.on_wall_time(3.5), s.on_wall_time(3.5)]  # period 2 times out
    s.await_command(3.5)
    trace += [s.on_wall_time(3.51), s.on_wall_time(3.51), s.lost]              # period 3 lost: zero
    s.await_command(3.51)
    out = s.on_command(3 * MS, torque(7))                # period 3's late answer: the loop is back
    trace += [out.step, out.resumed, s.lost, s.deadline]
    trace.append(s.on_command(4 * MS, torque(8)).step)
    s.await_command(4.0)
    trace += [s.on_command(5 * MS, torque(6)).step, s.done, s.on_command(6 * MS, torque(5)).step,
              s.done, s.k, s.on_period(), dict(s.counters)]
    return trace


def test_pipelined_keeps_every_waiting_rule_of_lockstep():
    """Pipelined differs from lockstep only in when the node steps the physics: what to wait
    for, how long, and what steps when a command is missing, late, refused or lost are the same."""
    lock, pipe = _waiting_rules_trace('lockstep'), _waiting_rules_trace('pipelined')
    assert len(lock) == len(pipe)
    for i, (a, b) in enumerate(zip(lock, pipe)):
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f'entry {i}')
        else:
            assert a == b, f'entry {i}: lockstep {a!r}, pipelined {b!r}'
    counters = lock[-1]                                  # and the script did exercise every rule
    assert (counters['timeouts'] == 1 and counters['safe_periods'] == 1
            and counters['late_command'] >= 1)
    assert counters['steps'] == 7 and lock[-3] == 7 and lock[-4] is True


def test_only_pipelined_steps_at_the_start_with_zero_torque():
    """The physics step t_0 → t_1 comes before any command in pipelined mode: the command that
    would drive it answers t_(−1)."""
    pipe = Stepping(N, MS, mode='pipelined')
    assert pipe.pipelined
    np.testing.assert_array_equal(pipe.start(), np.zeros((N, 2)))
    assert pipe.k == 0 and 'steps' not in pipe.counters   # the period is still 0's, awaiting its
                                                          # command
    for mode in ('lockstep', 'realtime'):
        s = Stepping(N, MS, mode=mode)
        assert s.start() is None and not s.pipelined
