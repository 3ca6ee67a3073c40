"""The input-to-motion delay a learned model lacks (analysis/loop_settings.unmodelled_delay),
measured on excitation stretches of a finger that is the model with its inputs late (a dead time,
a chamber's first-order pressure lag), and applied by the closed-loop check for every shape but the
hand's; bad values refused naming them."""
from dataclasses import replace
import math

from chamber_models import P_MAX, OneChamber, _chamber_facts, held_inputs
import numpy as np
import pytest

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.analysis import model_fitness as mf
from soft_gripper_sdre.sim.shape import ShapeError

DT = 0.01                                       # the chamber's tip period [s]


def _excitation(seed: int = 0, seconds: float = 20.0) -> np.ndarray:
    """(N, 1) pressures held for 50 to 300 ms each, 0 to half the range [Pa]."""
    return held_inputs(int(seconds / DT), 0.5 * P_MAX, seed)


def _finger(model, u: np.ndarray, dead: int = 0, lag: float = 0.0, noise: float = 2e-5,
            seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, u, tips) of ``model`` driven by ``u`` ``dead`` periods late through a first-order lag
    of ``lag`` [s], its tips at the model's rest plus noise [m]."""
    applied = np.concatenate([np.zeros((dead, 1)), u[:len(u) - dead]])
    if lag > 0:
        a, out = math.exp(-DT / lag), np.zeros_like(applied)
        for k in range(1, len(applied)):
            out[k] = a * out[k - 1] + (1 - a) * applied[k - 1]
        applied = out
    x = mf.simulate(model, np.zeros((1, 4)), applied[:-1, None, :], DT, substeps=4)[:, 0, :2]
    tips = model.rest_tip[:2] + x + noise * np.random.default_rng(seed).standard_normal(x.shape)
    tips[0] = model.rest_tip[:2]
    return np.arange(len(u)) * DT, u, tips


@pytest.mark.parametrize('dead', [0, 3, 6])
def test_a_dead_time_the_model_lacks_is_measured_to_a_fraction_of_a_period(dead):
    model = OneChamber()
    delay = ls.unmodelled_delay(model, *_finger(model, _excitation(), dead=dead))
    assert delay == pytest.approx(dead * DT, abs=0.3 * DT)


def test_a_first_order_pressure_lag_shows_as_a_delay_of_its_size():
    model = OneChamber()
    delay = ls.unmodelled_delay(model, *_finger(model, _excitation(), lag=0.05))
    assert 0.03 <= delay <= 0.07
    assert ls.delay_periods(delay, DT) in (3, 4, 5, 6, 7)


def test_the_check_applies_its_commands_the_delay_later():
    model = OneChamber()
    facts = _chamber_facts()
    settings = ls.settings_for(model, facts, 2.0, 1.0)
    late = ls.check_on_model(model, settings, replace(facts, input_delay=0.031))
    assert late == ls.check_on_model(model, settings, facts, delay=4)
    assert late != ls.check_on_model(model, settings, facts)


def test_a_finger_unlike_the_hand_is_checked_with_the_delay_its_data_show():
    model = OneChamber()
    excitation = [_finger(model, _excitation(seed, 8.0), dead=4, seed=seed + 10)
                  for seed in (0, 1)]
    derived = ls.derive(model, _chamber_facts(), bandwidths=(), excitation=excitation)
    assert derived.facts.input_delay == pytest.approx(4 * DT, abs=0.3 * DT)
    summary = derived.summary()
    assert summary['rules']['delay_periods'] == 5
    assert summary['facts']['input_delay'] == derived.facts.input_delay
    # without it the check is the one period of the hand's rule
    plain = ls.derive(model, _chamber_facts(), bandwidths=())
    assert plain.facts.input_delay == 0.0 and plain.summary()['rules']['delay_periods'] == 1
    assert 'input_delay' not in plain.summary()['facts']


class _Hand:
    """d = 2, m = 2: ẍ = −k p − c v + g u (the hand's shape)."""

    rest_tip = np.array([0.0, 0.1, 0.0])

    def AG(self, x):
        x = np.atleast_2d(x)
        A = np.zeros((len(x), 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0
        A[:, 2, 0] = A[:, 3, 1] = -900.0
        A[:, 2, 2] = A[:, 3, 3] = -10.0
        G = np.zeros((len(x), 4, 2))
        G[:, 2:, :] = np.array([[30.0, -5.0], [10.0, 40.0]])
        return A, G


def test_the_hand_shape_with_two_sided_inputs_keeps_its_rule():
    model = _Hand()
    rng = np.random.default_rng(3)
    u = np.repeat(rng.uniform(-0.02, 0.02, (100, 2)), 20, axis=0)
    applied = np.concatenate([np.zeros((5, 2)), u[:-5]])
    tips = model.rest_tip[:2] + mf.simulate(model, np.zeros((1, 4)), applied[:-1, None, :],
                                            DT, substeps=4)[:, 0, :2]
    excitation = [(np.arange(len(u)) * DT, u, tips)]
    assert ls.unmodelled_delay(model, *excitation[0]) == pytest.approx(5 * DT, abs=0.3 * DT)
    facts = ls.DataFacts(period=DT, noise_std=2e-5, travel=1e-4, torque_limit=0.02,
                         accel_psd_ml=1.0)
    derived = ls.derive(model, facts, bandwidths=(), excitation=excitation)
    assert derived.facts.input_delay == 0.0
    assert derived.summary()['rules']['delay_periods'] == 1
    assert 'input_delay' not in derived.summary()['facts']


@pytest.mark.parametrize('value', [-0.01, math.nan, math.inf])
def test_a_bad_input_delay_is_refused_naming_it(value):
    with pytest.raises(ShapeError, match='input delay'):
        _chamber_facts(input_delay=value)


@pytest.mark.parametrize('make, what', [
    (lambda t, u, p: (t, u[:, [0, 0]], p), r'inputs \(500, 1\)'),
    (lambda t, u, p: (t, u, p[:, :1]), r'tips \(500, 2\)'),
    (lambda t, u, p: (t[:50], u[:50], p[:50]), 'at least 100'),
    (lambda t, u, p: (t, np.where(np.arange(500)[:, None] == 7, math.nan, u), p), 'finite'),
    (lambda t, u, p: (t[::-1].copy(), u, p), 'increase'),
])
def test_bad_excitation_is_refused_naming_it(make, what):
    model = OneChamber()
    t, u, tips = _finger(model, _excitation(seconds=5.0))
    with pytest.raises(ShapeError, match=what):
        ls.unmodelled_delay(model, *make(t, u, tips))
