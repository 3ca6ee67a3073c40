"""Excitation plans and user-defined signals: the schedule, the limit, the finger, and every bad
spec refused naming the field."""
import numpy as np
import pytest
import yaml

from soft_gripper_sdre.sim.excitation import ExcitationPlan
from soft_gripper_sdre.sim.signal_specs import (
    SignalSpecError,
    builtin_signal,
    load_signal_specs,
    parse_signal_specs,
    resolve_signals,
)
from soft_gripper_sdre.sim.signals import get_signal

SPEC = {'signals': {
    'sines': {'kind': 'multisine', 'duration': 2.0,
              'ax0': {'amplitudes': [0.02, 0.01], 'frequencies': [0.5, 2.0], 'phases': [0.0, 1.0]},
              'ax1': {'amplitudes': [0.015], 'frequencies': [1.0], 'offset': 0.002}},
    'sweep': {'kind': 'chirp', 'duration': 4.0, 'ax0': {'amplitude': 0.03, 'f0': 0.5, 'f1': 2.5}},
    'logsweep': {'kind': 'chirp', 'duration': 4.0,
                 'ax1': {'amplitude': 0.01, 'f0': 0.1, 'f1': 10.0, 'method': 'logarithmic',
                         'phase': 0.5}},
}}


def test_user_multisine_and_chirps_are_what_the_spec_says(tmp_path):
    path = tmp_path / 'signals.yaml'
    path.write_text(yaml.safe_dump(SPEC))
    signals = load_signal_specs(path)
    t = np.linspace(0.0, 2.0, 201)
    u = signals['sines'].torque(t)
    np.testing.assert_allclose(u[:, 0],
                               0.02 * np.sin(np.pi * t) + 0.01 * np.sin(4 * np.pi * t + 1.0))
    np.testing.assert_allclose(u[:, 1], 0.002 + 0.015 * np.sin(2 * np.pi * t))
    # linear chirp: the phase is 2π(f0 t + (f1 − f0) t² / 2T); the other axis is zero
    t = np.linspace(0.0, 4.0, 401)
    u = signals['sweep'].torque(t)
    np.testing.assert_allclose(u[:, 0], 0.03 * np.sin(2 * np.pi * (0.5 * t + 0.25 * t * t)))
    assert np.all(u[:, 1] == 0.0) and signals['sweep'].duration == 4.0
    # logarithmic chirp: the instantaneous frequency goes from f0 to f1
    assert np.all(signals['logsweep'].torque(t)[:, 0] == 0.0)
    k = 100.0 ** (1 / 4.0)
    expected = 2 * np.pi * 0.1 * 4.0 / np.log(100.0) * (k ** t - 1.0) + 0.5
    np.testing.assert_allclose(signals['logsweep'].torque(t)[:, 1], 0.01 * np.sin(expected),
                               atol=1e-15)


BAD_SPECS = [
    ({'sig': {}}, 'must hold one mapping "signals:"'),
    ({'signals': {}}, '"signals" must map at least one name'),
    ({'signals': {'u1': SPEC['signals']['sweep']}}, "signals.u1: 'u1' is a built-in signal"),
    ({'signals': {'1bad': SPEC['signals']['sweep']}}, 'signals.1bad: a signal name is letters'),
    ({'signals': {'s': {'kind': 'square', 'duration': 1.0, 'ax0': {}}}},
     "signals.s.kind must be one of ['multisine', 'chirp']"),
    ({'signals': {'s': {'kind': 'chirp', 'ax0': {}}}}, "signals.s: missing field(s) ['duration']"),
    ({'signals': {'s': {'kind': 'chirp', 'duration': -1, 'ax0': {}}}},
     'signals.s.duration must be > 0'),
    ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0}}}, 'signals.s: define ax0, ax1 or both'),
    ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0, 'ax2': {}}}}, "unknown field(s) ['ax2']"),
    ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0,
                        'ax0': {'amplitude': 0.1, 'f0': 0, 'f1': 1}}}},
     'signals.s.ax0.f0 must be > 0'),
    ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0,
                        'ax0': {'amplitude': 0.1, 'f0': 1, 'f1': 1, 'method': 'cubic'}}}},
     "signals.s.ax0.method must be one of ['linear', 'logarithmic']"),
    ({'signals': {'s': {'kind': 'chirp', 'duration': 1.0,
                        'ax0': {'amplitude': '0.1', 'f0': 1, 'f1': 2}}}},
     "signals.s.ax0.amplitude must be a finite number, got '0.1'"),
    ({'signals': {'s': {'kind': 'multisine', 'duration': 1.0, 'ax1': {'amplitudes': [0.1, 0.2],
                                                                        'frequencies': [1.0]}}}},
     'signals.s.ax1: amplitudes, frequencies and phases must have the same length, got 2, 1 and 2'),
    ({'signals': {'s': {'kind': 'multisine', 'duration': 1.0,
                        'ax1': {'amplitudes': [], 'frequencies': []}}}},
     'signals.s.ax1.amplitudes must be a non-empty list'),
    ({'signals': {'s': {'kind': 'multisine', 'duration': 1.0,
                        'ax0': {'amplitudes': [0.1], 'frequencies': [float('nan')]}}}},
     'signals.s.ax0.frequencies[0] must be a finite number'),
    ({'signals': {'s': {'kind': 'multisine', 'duration': 1.0,
                        'ax0': {'amplitudes': [0.1], 'frequencies': [1e4]}}}},
     'signals.s.ax0.frequencies[0] must be > 0 and <= 500'),
]


@pytest.mark.parametrize('doc, message', BAD_SPECS)
def test_a_bad_spec_is_refused_naming_the_field(doc, message):
    with pytest.raises(SignalSpecError) as info:
        parse_signal_specs(doc, 'my.yaml')
    assert str(info.value).startswith('my.yaml') and message in str(info.value), str(info.value)


def test_spec_files_that_cannot_be_read(tmp_path):
    with pytest.raises(SignalSpecError, match='does not exist'):
        load_signal_specs(tmp_path / 'none.yaml')
    (tmp_path / 'bad.yaml').write_text('signals: [1\n')
    with pytest.raises(SignalSpecError, match=r'is not valid YAML \(line 2'):
        load_signal_specs(tmp_path / 'bad.yaml')


def test_resolve_names_built_in_and_user_signals(tmp_path):
    path = tmp_path / 's.yaml'
    path.write_text(yaml.safe_dump(SPEC))
    signals = resolve_signals(['u2', 'sweep'], path, duration=1.5)
    assert [(s.name, s.duration) for s in signals] == [('u2', 1.5), ('sweep', 1.5)]
    with pytest.raises(SignalSpecError, match="unknown signal 'sweep'.*need a spec file"):
        resolve_signals(['sweep'])
    with pytest.raises(SignalSpecError, match='at least one'):
        resolve_signals([])


def test_the_plan_settles_plays_each_signal_then_stays_at_zero():
    plan = ExcitationPlan([builtin_signal('u1', 1.0), builtin_signal('x1', 2.0)], settle_time=0.5,
                          n_fingers=1)
    assert plan.duration == 4.0 and [s.start for s in plan.segments] == [0.5, 2.0]
    for t in (0.0, 0.49, 1.5, 1.99, 4.0, 10.0):
        assert np.all(plan.torques(t) == 0.0), t
    np.testing.assert_array_equal(plan.torques(0.75)[0], get_signal('u1')(np.array([0.25]))[0])
    np.testing.assert_array_equal(plan.torques(3.5)[0], get_signal('x1')(np.array([1.5]))[0])
    assert plan.segment_at(3.0).signal.name == 'x1' and plan.segment_at(1.7) is None
    assert not plan.finished(3.999) and plan.finished(4.0)


def test_one_finger_and_the_torque_limit():
    plan = ExcitationPlan([builtin_signal('u1')], settle_time=0.0, n_fingers=4, finger=2,
                          torque_limit=0.03)
    u = np.array([plan.torques(t) for t in np.arange(0.0, 2.0, 0.01)])
    assert np.all(u[:, [0, 1, 3]] == 0.0)
    assert np.abs(u[:, 2]).max() == 0.03 and np.abs(u[:, 2]).min() < 0.03
    with pytest.raises(ValueError, match='finger must be in'):
        ExcitationPlan([builtin_signal('u1')], 0.0, n_fingers=1, finger=1)
    with pytest.raises(ValueError, match='torque_limit'):
        ExcitationPlan([builtin_signal('u1')], 0.0, n_fingers=1, torque_limit=0.0)
