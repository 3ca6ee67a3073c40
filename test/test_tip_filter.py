"""The estimator's loop rules (control/tip_filter.py) driven by plain calls: stamps and arrays, no
DDS. Every estimate is compared bit for bit with the KF stepped by hand."""
import numpy as np
import pytest

from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.tip_filter import GAP_PERIODS, Change, Notice, TipFilter

MS = 1_000_000
N = 4
Z = np.array([[0.001, -0.002], [0.0, 0.003], [0.002, 0.0], [0.0, 0.0]])
V = np.array([[0.01, 0.0], [0.0, -0.01], [0.0, 0.0], [0.02, 0.01]])
PREDICT = np.zeros(N, dtype=bool)


def meas(ns: int) -> np.ndarray:
    return Z + V * ns / 1e9


def make_filter(jump_ns=100 * MS, bridge_ns=50 * MS, period_ns=MS) -> TipFilter:
    return TipFilter(reference(period_ns), period_ns, jump_ns, bridge_ns)


def reference(period_ns=MS) -> ConstantVelocityKF:
    """The KF the rules drive, stepped by hand."""
    return ConstantVelocityKF(period_ns / 1e9, 1.0, 5e-5, n=N)


def state(f: TipFilter):
    return f.kf.x.copy(), f.kf.P.copy(), f.last_ns


def test_the_first_measurement_initialises_at_the_positions_with_zero_velocity():
    f = make_filter()
    out = f.on_tips(7 * MS, meas(7 * MS))
    assert out.refused is None and out.notices == (Notice(Change.INITIALISED, 7 * MS),)
    np.testing.assert_array_equal(out.estimate[:, :2], meas(7 * MS))
    np.testing.assert_array_equal(out.estimate[:, 2:], 0.0)
    assert f.last_ns == 7 * MS
    out.estimate[:] = 1.0                          # the estimate is the caller's copy
    assert not np.any(f.kf.x == 1.0)


def test_steps_on_the_grid_are_the_fixed_rate_filter_bit_for_bit():
    f, kf = make_filter(), reference()
    kf.reset(meas(0))
    expected = [kf.x.copy()] + [kf.step(meas(k * MS)) for k in range(1, 50)]
    got = []
    for k in range(50):
        out = f.on_tips(k * MS, meas(k * MS))
        first = (Notice(Change.INITIALISED, 0),)
        assert out.refused is None and out.notices == (() if k else first)
        got.append(out.estimate)
    np.testing.assert_array_equal(np.array(got), np.array(expected))
    assert +f.counters == {}
    assert f.take_mean_step() == MS and f.take_mean_step() is None


def test_a_gap_is_counted_and_predicted_through_period_by_period():
    f, kf = make_filter(), reference()
    f.on_tips(0, meas(0))
    f.on_tips(MS, meas(MS))
    out = f.on_tips(4 * MS, meas(4 * MS))                  # 2 periods lost: a gap, not a dropout
    kf.reset(meas(0))
    kf.step(meas(MS))
    kf.step(meas(4 * MS), PREDICT)
    kf.step(meas(4 * MS), PREDICT)
    np.testing.assert_array_equal(out.estimate, kf.step(meas(4 * MS)))
    assert out.notices == () and out.refused is None
    assert (f.counters['gaps'], f.counters['missed_periods']) == (1, 2)
    assert f.take_mean_step() == 2 * MS                    # (1 + 3) / 2 periods


def test_a_step_off_the_grid_is_one_step_over_the_stamp_difference():
    f, kf = make_filter(), reference()
    f.on_tips(0, meas(0))
    out = f.on_tips(MS + MS // 2, meas(MS + MS // 2))      # 1.5 periods: not yet a gap
    kf.reset(meas(0))
    np.testing.assert_array_equal(out.estimate, kf.step(meas(MS + MS // 2), dt=1.5e-3))
    assert +f.counters == {}
    out = f.on_tips(4 * MS, meas(4 * MS))          # 2.5 periods: a gap, counted as 2 lost
    np.testing.assert_array_equal(out.estimate, kf.step(meas(4 * MS), dt=2.5e-3))
    assert (f.counters['gaps'], f.counters['missed_periods']) == (1, 2)


def test_jittery_stamps_within_the_gap_bound_raise_nothing():
    rng = np.random.default_rng(5)
    period = 10 * MS
    stamps = period * np.arange(200) + (rng.uniform(-0.2, 0.2, 200) * period).astype(int)
    f = make_filter(period_ns=period)
    for stamp in stamps:
        out = f.on_tips(int(stamp), meas(int(stamp)))
        assert out.estimate is not None and out.refused is None
        assert all(n.change is Change.INITIALISED for n in out.notices)
    assert +f.counters == {} and GAP_PERIODS * period > np.diff(stamps).max()
    assert f.take_mean_step() == pytest.approx(period, rel=0.01)


def test_a_gap_longer_than_max_bridge_is_a_dropout_still_predicted_through():
    f, kf = make_filter(bridge_ns=20 * MS), reference()
    kf.reset(meas(0))
    stamps = [0, MS, 2 * MS, 12 * MS, 42 * MS, 43 * MS]        # 9 then 29 periods lost
    for last, stamp in zip([None] + stamps, stamps):
        out = f.on_tips(stamp, meas(stamp))
        if last is None:
            continue
        for _ in range((stamp - last) // MS - 1):
            kf.step(meas(stamp), PREDICT)
        np.testing.assert_array_equal(out.estimate, kf.step(meas(stamp)))
        assert out.notices == ((Notice(Change.DROPOUT, stamp, last),) if stamp == 42 * MS else ())
    assert (f.counters['gaps'], f.counters['missed_periods']) == (2, 38)
    assert f.counters['dropouts'] == f.counters['resets'] == 0     # the caller counts its problems


@pytest.mark.parametrize('stamp', [0, 60 * MS])
def test_a_jump_either_way_resets_and_initialises_again(stamp):
    f = make_filter(jump_ns=10 * MS)
    for k in range(10, 21):
        f.on_tips(k * MS, meas(k * MS))
    out = f.on_tips(stamp, meas(stamp))
    assert out.notices == (Notice(Change.RESET, stamp, 20 * MS), Notice(Change.INITIALISED, stamp))
    np.testing.assert_array_equal(out.estimate[:, :2], meas(stamp))
    np.testing.assert_array_equal(out.estimate[:, 2:], 0.0)
    assert f.last_ns == stamp and +f.counters == {}
    kf = reference()
    kf.reset(meas(stamp))
    after = f.on_tips(stamp + MS, meas(stamp + MS)).estimate
    np.testing.assert_array_equal(after, kf.step(meas(stamp + MS)))


def test_a_jump_of_exactly_reset_jump_is_a_gap_not_a_reset():
    f = make_filter(jump_ns=10 * MS, bridge_ns=50 * MS)
    f.on_tips(0, meas(0))
    out = f.on_tips(10 * MS, meas(10 * MS))
    assert out.notices == () and f.counters['missed_periods'] == 9
    assert f.on_tips(0, meas(0)).refused == 'out_of_order'      # 10 ms back: an old message


@pytest.mark.parametrize('stamp, kind', [(9 * MS, 'duplicate'), (8 * MS, 'out_of_order'),
                                         (5 * MS, 'out_of_order')])
def test_duplicates_and_late_messages_are_refused_leaving_the_filter_untouched(stamp, kind):
    f = make_filter(jump_ns=10 * MS)
    for k in range(10):
        f.on_tips(k * MS, meas(k * MS))
    before = state(f)
    out = f.on_tips(stamp, meas(stamp) + 1.0)
    assert (out.estimate, out.refused, out.notices) == (None, kind, ())
    assert f'{stamp} ns' in out.reason and f'{9 * MS} ns' in out.reason
    after = state(f)
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1], before[1])
    assert after[2] == before[2] and +f.counters == {}


@pytest.mark.parametrize('bad', [np.vstack([Z, [[0.0, 0.0]]]), Z[:3], Z[:, :1], np.zeros((0, 2)),
                                 np.where(np.arange(8).reshape(4, 2) == 5, np.nan, Z),
                                 np.where(np.arange(8).reshape(4, 2) == 0, -np.inf, Z)])
@pytest.mark.parametrize('first', [True, False])
def test_malformed_positions_are_refused_leaving_the_filter_untouched(bad, first):
    f = make_filter()
    if not first:
        f.on_tips(0, meas(0))
    before = state(f)
    out = f.on_tips(MS, bad)
    assert (out.estimate, out.refused, out.notices) == (None, 'bad_message', ())
    assert 'finite' in out.reason
    after = state(f)
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1], before[1])
    assert after[2] == before[2]
    assert f.on_tips(MS, meas(MS)).estimate is not None           # the next good one is taken


def test_reset_jump_and_max_bridge_may_change_between_calls():
    f = make_filter(jump_ns=100 * MS, bridge_ns=50 * MS)
    f.on_tips(0, meas(0))
    assert f.on_tips(31 * MS, meas(31 * MS)).notices == ()          # 30 ms lost: bridged quietly
    f.max_bridge_ns = 20 * MS
    assert f.on_tips(62 * MS, meas(62 * MS)).notices == (Notice(Change.DROPOUT, 62 * MS, 31 * MS),)
    f.reset_jump_ns = 20 * MS
    assert [n.change for n in f.on_tips(93 * MS, meas(93 * MS)).notices] == [Change.RESET,
                                                                            Change.INITIALISED]


def test_counters_go_where_the_caller_keeps_them():
    from collections import Counter
    counters = Counter(received=3)
    f = TipFilter(reference(), MS, 100 * MS, 50 * MS, counters=counters)
    f.on_tips(0, meas(0))
    f.on_tips(3 * MS, meas(3 * MS))
    assert f.counters is counters and counters == Counter(received=3, gaps=1, missed_periods=2)
