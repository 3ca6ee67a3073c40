"""The excitation level: the amplitude scale of the plan, its share at the clip, and the level
search against a simulated linear spring–damper finger (no ROS)."""
import math

import numpy as np
import pytest
from spring_finger import NOISE, RATE, REST, SpringDamper

from soft_gripper_sdre.sim.excitation import ExcitationPlan, LevelSearch, LevelSettings
from soft_gripper_sdre.sim.signal_specs import builtin_signal
from soft_gripper_sdre.sim.signals import BROADBAND_SIGNALS, SIGNALS


def run_search(search: LevelSearch, plant: SpringDamper, limit: float = 120.0) -> int:
    """Drive ``search`` with the plant's tips until it is done; returns the tips it took."""
    for k in range(int(limit * RATE)):
        u = search.step(k / RATE, plant.tips())
        if search.done:
            return k
        plant.step(u[0])
    raise AssertionError(f'no amplitude after {limit} s: probes {search.probes}')


def peak_excursion(plan: ExcitationPlan, plant: SpringDamper) -> float:
    peak = 0.0
    for k in range(int(plan.duration * RATE)):
        peak = max(peak, float(np.linalg.norm(plant.tips()[0] - REST)))
        plant.step(plan.torques(k / RATE)[0])
    return peak


def test_amplitude_scales_every_signal_before_the_clip_and_one_keeps_them_bit_for_bit():
    t = np.arange(0.0, 10.0, 0.0137)
    for name, torque in SIGNALS.items():
        plan = ExcitationPlan([builtin_signal(name)], settle_time=0.0, n_fingers=1)
        got = np.array([plan.torques(x)[0] for x in t])
        expected = np.clip(torque(t), -0.1, 0.1)
        assert got.tobytes() == expected.tobytes(), name
    plan = ExcitationPlan([builtin_signal('u1')], 0.0, 1, torque_limit=0.05, amplitude=0.5)
    np.testing.assert_array_equal(plan.torques(0.5)[0], 0.5 * SIGNALS['u1'](np.array([0.5]))[0])
    assert np.all(plan.scaled(2.0).torques(0.5)[0] == 0.05)        # 2 × 0.0625 clipped to 0.05
    with pytest.raises(ValueError, match='amplitude must be finite and > 0'):
        ExcitationPlan([builtin_signal('u1')], 0.0, 1, amplitude=0.0)
    with pytest.raises(ValueError, match='amplitude must be finite and > 0'):
        plan.scaled(float('nan'))


def test_clip_share_and_the_largest_unclipped_amplitude():
    plan = ExcitationPlan([builtin_signal('u1')], settle_time=0.5, n_fingers=1,
                          torque_limit=0.03125)
    np.testing.assert_allclose(plan.peak_torque, [0.0625, 0.0625], rtol=1e-9)
    assert plan.largest_unclipped_amplitude() == pytest.approx(0.5, rel=1e-9)
    # |sin| >= 1/2 two thirds of the time
    assert plan.clip_share() == pytest.approx(2 / 3, abs=2e-3)
    assert plan.clip_share(0.4) == 0.0 and plan.scaled(0.4).clip_share() == 0.0
    assert 0.99 < plan.clip_share(100.0) < 1.0                      # all but the zero crossings


@pytest.mark.parametrize('name', list(SIGNALS))
def test_the_search_lands_the_signal_near_the_target_off_the_clip(name):
    """One signal per run (one bag per signal, as tools.graph.excite records them)."""
    max_excursion, target = 0.02, 0.5
    goal = target * max_excursion
    plan = ExcitationPlan([builtin_signal(name)], 0.5, 1, torque_limit=0.1)
    search = LevelSearch(plan.peak_torque, 0.1, max_excursion, 1,
                         settings=LevelSettings(target=target, settle_time=0.5))
    run_search(search, SpringDamper())
    amps = [p.amplitude for p in search.probes]
    assert amps[0] == 0.05 and all(b > a for a, b in zip(amps, amps[1:]))
    assert all(b <= 2 * a * (1 + 1e-12) for a, b in zip(amps, amps[1:])), amps
    assert all(p.excursion < max_excursion for p in search.probes)
    last = search.probes[-1]
    assert last.excursion >= 0.8 * goal and search.amplitude <= 2 * last.amplitude
    assert search.amplitude == pytest.approx(last.amplitude * goal / last.excursion)
    assert search.end == pytest.approx(0.5 + len(amps) * 2.5)
    np.testing.assert_allclose(search.rest[0], REST, atol=4 * NOISE / math.sqrt(100))
    scaled = plan.scaled(search.amplitude)
    assert scaled.clip_share() == 0.0
    peak = peak_excursion(scaled, SpringDamper(seed=1))
    # a broadband signal's many components never add up the way the probe's one sine does: it
    # lands under the target, never over it
    low = goal / 4 if name in BROADBAND_SIGNALS else goal / 1.5
    assert low <= peak <= goal * 1.5, (amps, search.amplitude, peak)


def test_a_stiff_finger_stops_the_search_at_the_torque_limit():
    plan = ExcitationPlan([builtin_signal('x1')], 0.5, 1, torque_limit=0.02)
    search = LevelSearch(plan.peak_torque, 0.02, 0.02, 1, settings=LevelSettings(settle_time=0.5))
    run_search(search, SpringDamper(gain=0.01))
    largest = plan.largest_unclipped_amplitude()
    assert search.probes[-1].amplitude == pytest.approx(largest)
    assert search.amplitude == pytest.approx(largest)
    assert plan.clip_share(search.amplitude) <= 1e-4           # the peak sample touches it
    # capped: the excursion expected there, the last probe's, is short of the goal (reported)
    assert search.capped and search.expected == pytest.approx(search.probes[-1].excursion)
    assert search.expected < search.goal
    assert all(np.all(np.abs(search.probe_torque(s, largest)) <= 0.02 * (1 + 1e-12))
               for s in np.linspace(0.0, 2.0, 101))


def test_a_soft_finger_is_scaled_down_from_the_first_probe():
    plan = ExcitationPlan([builtin_signal('u1')], 0.5, 1)
    search = LevelSearch(plan.peak_torque, 0.1, 0.02, 1,
                         settings=LevelSettings(settle_time=0.5, start=0.2))
    run_search(search, SpringDamper())
    [probe] = search.probes
    assert probe.excursion > 0.01 and search.amplitude < 0.2
    assert not search.capped and search.expected == pytest.approx(search.goal)


def test_probes_excite_only_the_chosen_finger_and_zero_settles_between():
    search = LevelSearch(np.array([0.06, 0.03]), 0.1, 0.02, 3, finger=1,
                         settings=LevelSettings(settle_time=0.5, probe_time=2.0))
    tips = np.tile(REST, (3, 1))
    assert np.all(search.step(0.1, tips) == 0.0)                  # the first settle
    u = search.step(0.5 + 0.25, tips)                             # a quarter period in
    np.testing.assert_allclose(u[1], [0.05 * 0.06, 0.05 * 0.03])
    assert np.all(u[[0, 2]] == 0.0)
    u = search.step(0.5 + 1.25, tips)                             # the axes in opposite phase
    np.testing.assert_allclose(u[1], [0.05 * 0.06, -0.05 * 0.03])
    assert np.all(search.step(0.5 + 2.2, tips) == 0.0)            # settling after the probe


@pytest.mark.parametrize('kwargs, settings, message', [
    (dict(peak=np.zeros(2)), {}, 'peak must be'),
    (dict(max_excursion=0.0), {}, 'max_excursion must be finite and > 0'),
    ({}, dict(target=1.5), 'target must be in (0, 1]'),
    ({}, dict(start=0.0), 'start must be finite and > 0'),
    ({}, dict(ratio=1.0), 'ratio must be finite and > 1'),
    ({}, dict(probe_time=0.0), 'probe_time must be finite and > 0'),
    ({}, dict(settle_time=0.0), 'settle_time must be finite and > 0'),
    (dict(finger=2), {}, 'finger must be in [0, 0]'),
])
def test_bad_search_arguments_are_named(kwargs, settings, message):
    args = dict(peak=np.array([0.06, 0.06]), torque_limit=0.1, max_excursion=0.02, n_fingers=1)
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        LevelSearch(**args, settings=LevelSettings(**settings))
    assert message in str(info.value)

