"""Excitation for fingers of m inputs with per-input bounds (no ROS): the built-in signals as
shares for 1 to 4 inputs, plans that keep every input in its interval (about the middle of a
two-sided one, from the rest value into a one-sided one), spec files with ax0..ax<m−1>, and the
level search on the real pneumatic (m = 1) and trunk (m = 3) fingers of sim/plants/presets."""
import dataclasses

import numpy as np
import pytest
import yaml

from soft_gripper_sdre.sim.excitation import ExcitationPlan, LevelSearch, LevelSettings
from soft_gripper_sdre.sim.plants.pneumatic import P_MAX
from soft_gripper_sdre.sim.plants.presets import make_plant
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.sim.signal_specs import (
    Signal,
    SignalSpecError,
    builtin_signal,
    parse_signal_specs,
    resolve_signals,
)
from soft_gripper_sdre.sim.signals import REFERENCE, SIGNALS, U4_PERIOD, input_signal, u4_delays

T = np.arange(0.0, 10.0, 1e-3)
CHAMBER = InputBounds([0.0], [P_MAX])
TENDONS = InputBounds(np.zeros(3), np.full(3, 4.0))


@pytest.mark.parametrize('name', list(SIGNALS))
def test_the_built_in_signals_as_shares_for_one_to_four_inputs(name):
    """Two inputs: the hand's torques over 0.1 N·m; every m: within ±1, the paper's signals the
    same on every input (u4 only for one or two inputs: test_u4_is_staggered_…), the identifying
    and broadband ones uncorrelated between inputs."""
    np.testing.assert_allclose(input_signal(name, 2)(T) * 0.1, SIGNALS[name](T), atol=1e-15)
    for m in (1, 2, 3, 4):
        s = input_signal(name, m)(T)
        assert s.shape == (T.size, m) and np.abs(s).max() <= 1.0 and np.abs(s).max() > 0.3
        if name.startswith('u') and (name != 'u4' or m <= 2):
            assert np.all(s == s[:, :1])
        elif m > 1 and name != 'u4':
            corr = np.corrcoef(s.T) - np.eye(m)
            assert np.abs(corr).max() < 0.2, (m, corr)
            assert np.all(s.min(axis=0) < -0.2) and np.all(s.max(axis=0) > 0.2)
    with pytest.raises(ValueError, match='the number of inputs m must be 1 to 4, got 5'):
        input_signal(name, 5)
    with pytest.raises(KeyError, match='known signals'):
        input_signal('u9', 2)


@pytest.mark.parametrize('m', [3, 4])
def test_u4_is_staggered_over_three_or_four_inputs(m):
    """Input k plays u4 delayed by k/m of its 2 s period: each input u4's own values; the
    inputs no longer equal, their mean over the inputs only u4's 1.5 Hz part for three inputs
    (its 0.5 and 1 Hz parts cancel) and nothing for four."""
    one = input_signal('u4', 1)
    s = input_signal('u4', m)(T)
    assert s.shape == (T.size, m)
    np.testing.assert_array_equal(u4_delays(m), np.arange(m) * U4_PERIOD / m)
    for k in range(m):
        np.testing.assert_allclose(s[:, k], one(T - k * U4_PERIOD / m)[:, 0], atol=1e-15)
        np.testing.assert_allclose(np.abs(s[:, k]).max(), np.abs(one(T)).max(), rtol=1e-3)
    common = 6 * np.sin(3 * np.pi * T) / REFERENCE if m == 3 else np.zeros_like(T)
    np.testing.assert_allclose(s.mean(axis=1), common, atol=1e-12)
    assert np.abs(np.corrcoef(s.T) - np.eye(m)).max() < 0.5
    np.testing.assert_array_equal(input_signal('u4', m)(0.25), s[250])
    np.testing.assert_array_equal(u4_delays(2), [0.0, 0.0])
    np.testing.assert_array_equal(u4_delays(1), [0.0])
    np.testing.assert_array_equal(u4_delays(1, one_sided=True), [0.0])
    np.testing.assert_array_equal(input_signal('u4', m, one_sided=True)(T), s)


def test_u4_is_staggered_over_two_inputs_that_only_pull_and_alike_over_two_that_push_and_pull():
    """Two one-sided inputs: the second plays u4 a half period later, so its 0.5 and 1.5 Hz
    parts are in antiphase on the pair (their difference) and its 1 Hz part common (their
    mean); two bidirectional inputs keep the hand's u4, both equal; the other signals do not
    depend on it."""
    one = input_signal('u4', 1)(T)[:, 0]
    pair = input_signal('u4', 2, one_sided=True)(T)
    np.testing.assert_array_equal(u4_delays(2, one_sided=True), [0.0, U4_PERIOD / 2])
    np.testing.assert_allclose(pair[:, 0], one, atol=1e-15)
    np.testing.assert_allclose(pair[:, 1], input_signal('u4', 1)(T - 1.0)[:, 0], atol=1e-15)
    np.testing.assert_allclose(pair.mean(axis=1), 7 * np.sin(2 * np.pi * T) / REFERENCE,
                               atol=1e-12)
    np.testing.assert_allclose(pair[:, 0] - pair[:, 1],
                               2 * (6 * np.sin(3 * np.pi * T) + 8 * np.sin(np.pi * T)) / REFERENCE,
                               atol=1e-12)
    both = input_signal('u4', 2)(T)
    np.testing.assert_array_equal(both[:, 0], both[:, 1])
    assert builtin_signal('u4', m=2, one_sided=True).torque(T)[:, 1] @ one < 0
    for name in set(SIGNALS) - {'u4'}:
        np.testing.assert_array_equal(input_signal(name, 2, one_sided=True)(T),
                                      input_signal(name, 2)(T))
    names = resolve_signals(['u1', 'u4'], m=2, one_sided=True)
    np.testing.assert_array_equal(names[1].torque(T), pair)


def _u4_alike(m: int) -> Signal:
    """u4 the same on all ``m`` inputs, 4 s (the shares of one input's u4 repeated)."""
    one = input_signal('u4', 1)
    return Signal('u4', 4.0, lambda t: np.repeat(one(t), m, axis=-1), share=True)


def _tip_spread(preset: str, signal: Signal, bounds: InputBounds, level: float,
                dt: float) -> np.ndarray:
    """The standard deviation per coordinate [m] of the preset finger's tip about its rest while
    ``signal`` plays at ``level`` after a 0.5 s settle, every input within ``bounds``."""
    plant = make_plant(preset)
    plan = ExcitationPlan([signal], 0.5, 1, bounds=bounds).scaled(level)
    tips = []
    for k in range(int(plan.duration / dt)):
        u = plan.torques(k * dt)[0]
        assert bounds.contains(u)
        plant.step(u, dt)
        tips.append(plant.tip() - plant.rest_tip)
    return np.std(tips, axis=0)


def test_staggered_u4_bends_the_trunk_segment_where_u4_alike_only_shortens_it():
    """On the real three-tendon segment (trunk3_a, from slack at the level the recipe's search
    found, 0.45): u4 alike on the three tendons moves the tip along the segment's axis alone;
    staggered, the same tendons within [0, 4 N] bend it across the axis in both directions by
    more than half its motion along it."""
    spread = {name: _tip_spread('trunk3_a', signal, TENDONS, 0.45, 0.004)
              for name, signal in (('staggered', builtin_signal('u4', 4.0, m=3)),
                                   ('alike', _u4_alike(3)))}   # (x along the segment, y, z) [m]
    assert np.all(spread['alike'][1:] < 1e-9) and spread['alike'][0] > 1e-3
    assert np.all(spread['staggered'][1:] > 0.5 * spread['staggered'][0])
    assert np.all(spread['staggered'][1:] > 0.5e-3)


def test_staggered_u4_moves_the_flexor_extensor_finger_that_u4_alike_hardly_moves():
    """On the real flexor/extensor finger (flexor2_index: two tendons pulling the tip 167°
    apart, from slack at a level the recipe's search chooses, 0.6 of [0, 4 N]): u4 alike on the
    two tendons moves the tip less than half as far as the same tendons staggered."""
    bounds = InputBounds(np.zeros(2), np.full(2, 4.0))
    spread = {name: float(np.linalg.norm(_tip_spread('flexor2_index', signal, bounds, 0.6, 0.005)))
              for name, signal in (('staggered', builtin_signal('u4', 4.0, m=2, one_sided=True)),
                                   ('alike', _u4_alike(2)))}
    assert spread['staggered'] > 2 * spread['alike'], spread
    assert spread['staggered'] > 2e-3, spread


def test_one_input_gets_two_different_broadband_and_identifying_signals():
    """b1/b2 and x1/x2 on one input are not the same record twice: uncorrelated."""
    for a, b in (('b1', 'b2'), ('x1', 'x2')):
        corr = np.corrcoef(input_signal(a, 1)(T)[:, 0], input_signal(b, 1)(T)[:, 0])[0, 1]
        assert abs(corr) < 0.1, (a, b, corr)


def _inputs(plan, dt=0.004):
    return np.array([plan.torques(t) for t in np.arange(0.0, plan.duration + 0.2, dt)])


def test_a_one_sided_input_moves_from_its_rest_value_into_the_interval():
    """A chamber 0..p_max: zero while settling and after the end, the signal inside
    [0, a·p_max] — never below the rest value, never above p_max even when scaled past it."""
    plan = ExcitationPlan(resolve_signals(['u1', 'x1', 'b1'], duration=2.0, m=1), 0.5, 2,
                          bounds=CHAMBER)
    u = _inputs(plan)
    assert u.shape[1:] == (2, 1) and plan.m == 1
    assert np.all(u >= 0.0) and np.all(u <= P_MAX) and u.max() > 0.5 * P_MAX
    np.testing.assert_array_equal(plan.torques(0.2), [[0.0], [0.0]])
    np.testing.assert_array_equal(plan.torques(plan.duration), [[0.0], [0.0]])
    playing = np.array([plan.torques(t) for t in np.arange(0.5, 2.5, 0.002)])[:, 0, 0]
    assert playing.min() > 0.1 * P_MAX                  # u1 = 0.625 sin: 0.19 … 0.81 p_max
    assert np.mean(playing) == pytest.approx(0.5 * P_MAX, rel=0.05)
    big = plan.scaled(2.5)
    u = _inputs(big)
    assert np.all(u >= 0.0) and np.all(u <= P_MAX) and np.any(u == P_MAX)
    assert big.clip_share() > 0.1 and plan.clip_share() == 0.0
    largest = plan.largest_unclipped_amplitude()
    assert 1.0 < largest < 2.5
    assert plan.clip_share(largest * 0.999) == 0.0 and plan.clip_share(largest * 1.01) > 0.0


def test_two_sided_bounds_are_played_about_their_middle_and_tendons_from_slack():
    motor = InputBounds([-0.05, -0.2], [0.15, 0.2])
    plan = ExcitationPlan(resolve_signals(['x1'], m=2), 0.0, 1, bounds=motor)
    u = _inputs(plan, 0.001)[:, 0]
    assert motor.contains(u)
    np.testing.assert_allclose(u[:-200].mean(axis=0), motor.mid, atol=0.005)
    plan = ExcitationPlan(resolve_signals(['x2', 'u3'], m=3), 0.3, 1, bounds=TENDONS,
                          amplitude=1.5)
    u = _inputs(plan)[:, 0]
    assert TENDONS.contains(u) and np.all(u.max(axis=0) > 2.0)
    np.testing.assert_array_equal(plan.torques(0.1), np.zeros((1, 3)))
    nonzero = InputBounds([0.01, 0.02, 0.03], [4.0, 4.0, 4.0])   # a tendon kept taut
    plan = ExcitationPlan(resolve_signals(['u1'], m=3), 0.3, 2, finger=1, bounds=nonzero)
    np.testing.assert_array_equal(plan.torques(0.1), [[0.01, 0.02, 0.03]] * 2)
    np.testing.assert_array_equal(plan.torques(1.0)[0], [0.01, 0.02, 0.03])
    assert nonzero.contains(_inputs(plan))


def test_signals_for_another_number_of_inputs_are_refused():
    with pytest.raises(ValueError, match="signal 'u1' gives 2 input.s.; the finger has 3"):
        ExcitationPlan([builtin_signal('u1')], 0.0, 1, bounds=TENDONS)
    with pytest.raises(ValueError, match="signal 'x1' gives 1 input.s.; the finger has 3"):
        ExcitationPlan([builtin_signal('x1', m=1)], 0.0, 1, bounds=TENDONS)


def test_spec_files_for_m_inputs_name_ax0_to_ax_m_minus_1_in_the_inputs_units():
    doc = {'signals': {'pull': {'kind': 'multisine', 'duration': 1.0,
                                'ax2': {'amplitudes': [1.0], 'frequencies': [2.0],
                                        'offset': 2.0}}}}
    sig = parse_signal_specs(doc, 'my.yaml', m=3, limit=40.0)['pull']
    u = sig.torque(np.array([0.0, 0.125]))
    np.testing.assert_allclose(u, [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    plan = ExcitationPlan([sig], 0.0, 1, amplitude=2.0, bounds=TENDONS)
    np.testing.assert_allclose(plan.torques(0.125), [[0.0, 0.0, 4.0]])      # 6 N clipped
    bad = [
        ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0, 'ax3': {}}}}, 3, 40.0,
         "my.yaml: signals.s: unknown field(s) ['ax3']; allowed: kind, duration, ax0, ax1, ax2"),
        ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0}}}, 3, 40.0,
         'signals.s: define at least one of ax0, ax1, ax2'),
        ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0}}}, 1, 40.0,
         'signals.s: define ax0 (an axis'),
        ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0, 'ax1': {}}}}, 1, 40.0,
         "unknown field(s) ['ax1']"),
        ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0,
                            'ax0': {'amplitude': 7e5, 'f0': 1.0, 'f1': 2.0}}}}, 1, 6e5,
         'signals.s.ax0.amplitude must be >= 0 and <= 600000'),
    ]
    for doc, m, limit, message in bad:
        with pytest.raises(SignalSpecError) as info:
            parse_signal_specs(doc, 'my.yaml', m=m, limit=limit)
        assert message in str(info.value), str(info.value)


def _search_on(plant, bounds: InputBounds, names, target_mm: float):
    """The level search on a real foreign finger at 200 Hz; (search, inputs it sent (N, m))."""
    plan = ExcitationPlan(resolve_signals(names, duration=4.0, m=bounds.m), 0.5, 1,
                          bounds=bounds)
    search = LevelSearch(plan.peak_torque, 1.0, 2 * target_mm * 1e-3, 1,
                         settings=LevelSettings(probe_time=1.0, settle_time=0.5),
                         inputs=plan.probe_inputs())
    sent, dt = [], 0.005
    for k in range(int(60 / dt)):
        tips = np.zeros((1, 3))
        tips[0, :plant.shape.d] = plant.tip()
        u = search.step(k * dt, tips)
        if search.done:
            return plan.scaled(search.amplitude), search, np.array(sent)
        sent.append(u[0])
        plant.step(u[0], dt)
    raise AssertionError(f'no amplitude: {search.probes}')


@pytest.mark.parametrize('preset, bounds, names', [
    ('pneumatic1_a', CHAMBER, ['u1', 'x1']),
    ('trunk3_a', TENDONS, ['x1', 'b1']),
])
def test_the_level_search_probes_within_the_bounds_and_reaches_its_target(preset, bounds, names):
    """Probes from rest into the interval, never outside it; the chosen amplitude plays the
    signals to 60–150 % of the 8 mm aimed at on the same finger, within the bounds."""
    plant = make_plant(preset)
    plan, search, sent = _search_on(plant, bounds, names, target_mm=8.0)
    assert bounds.contains(sent) and sent.shape[1] == bounds.m
    assert np.all(sent.min(axis=0) == 0.0) and np.all(sent.max(axis=0) > 0.0)
    assert len(search.probes) >= 2 and 0 < search.amplitude <= plan.largest_unclipped_amplitude()
    plant.reset()
    peak, dt = 0.0, 0.005
    for k in range(int(plan.duration / dt)):
        u = plan.torques(k * dt)[0]
        assert bounds.contains(u)
        plant.step(u, dt)
        peak = max(peak, float(np.linalg.norm(plant.tip() - plant.rest_tip)))
    assert 0.6 * 8e-3 < peak < 1.5 * 8e-3, peak


def test_level_auto_needs_one_kind_of_signal_with_bounds(tmp_path):
    path = tmp_path / 's.yaml'
    path.write_text(yaml.safe_dump({'signals': {'mine': {
        'kind': 'chirp', 'duration': 1.0, 'ax0': {'amplitude': 1.0, 'f0': 1.0, 'f1': 2.0}}}}))
    plan = ExcitationPlan(resolve_signals(['u1', 'mine'], path, m=3, limit=40.0), 0.0, 1,
                          bounds=TENDONS)
    with pytest.raises(ValueError, match='all built-in or all from spec_file'):
        plan.probe_inputs()
    with pytest.raises(ValueError, match='probe inputs need a plan with bounds'):
        ExcitationPlan([builtin_signal('u1')], 0.0, 1).probe_inputs()
    probe = ExcitationPlan(resolve_signals(['u1'], m=3), 0.0, 1, bounds=TENDONS).probe_inputs()
    for bad in (dataclasses.replace(probe, largest=0.0),
                dataclasses.replace(probe, swing=np.zeros(3))):
        with pytest.raises(ValueError, match='room within their bounds'):
            LevelSearch(np.ones(2), 1.0, 0.01, 1, inputs=bad)
