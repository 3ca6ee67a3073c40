"""The derived settings for fingers unlike the hand (analysis/loop_settings.py, holding.py,
data_facts.py): a one-chamber finger with a planar tip (d = 2, m = 1, pressure 0..p_max), whose
move follows the curve of its equilibria, and a three-tendon segment with a 3-D tip (d = 3,
m = 3, pull-only tendons), each checked in closed loop on the model with the real laws within
its one-sided bounds; bad values refused naming them."""
import math

from chamber_models import (
    P_MAX,
    SHORT_PROFILE,
    T_MAX,
    OneChamber,
    ThreeTendons,
    _chamber_facts,
    _tendon_facts,
)
import numpy as np
import pytest

from soft_gripper_sdre.analysis import data_facts as df
from soft_gripper_sdre.analysis import holding
from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.analysis import model_fitness as mf
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds, ShapeError


def test_the_shape_is_read_off_models_that_only_have_AG():
    assert mf.model_shape(OneChamber()) == FingerShape(2, 1)
    assert mf.model_shape(ThreeTendons()) == FingerShape(3, 3)


def test_the_equilibria_of_one_input_lie_on_a_curve_the_input_sweeps_from_rest():
    model = OneChamber()
    axis = np.array([0.5, math.sqrt(3) / 2])
    curve = holding.equilibrium_curve(model, InputBounds([0.0], [P_MAX]), axis)
    assert curve.inputs[0, 0] == 0.0 and curve.inputs[-1, 0] == pytest.approx(P_MAX)
    assert np.all(np.diff(curve.inputs[:, 0]) > 0)
    np.testing.assert_array_equal(curve.points[0], [0.0, 0.0])
    for u, p in zip(curve.inputs[:, 0], curve.points):
        assert np.abs(model.statics(p, u)).max() < 1e-6           # A21(p) p + G2(p) u = 0
    # a curve, not a line: the hardening at 3 mm along X turns it toward Y
    first, last = curve.points[5] / np.linalg.norm(curve.points[5]), \
        curve.points[-1] / np.linalg.norm(curve.points[-1])
    assert math.degrees(math.acos(first @ last)) > 10
    # cut by arc length from rest
    cut = curve.cut(4e-3, 9)
    assert np.linalg.norm(np.diff(cut, axis=0), axis=1).sum() == pytest.approx(4e-3, rel=1e-3)
    # the inputs of half the range hold the curve only up to where the pressure reaches half
    held = curve.holdable_length(holding.hold_bounds(InputBounds([0.0], [P_MAX])))
    half = np.flatnonzero(curve.inputs[:, 0] <= P_MAX / 2)[-1]
    assert held == pytest.approx(curve.arc[half])


def test_a_one_sided_input_sweeps_toward_its_only_side():
    """Asked for the way the pressure cannot push (−axis), the curve still goes where the
    chamber can: a pull-only (negative) input likewise."""
    model = OneChamber()
    up = holding.equilibrium_curve(model, InputBounds([0.0], [P_MAX]), np.array([-0.5, -0.8]))
    assert np.all(up.inputs >= 0) and up.points[-1] @ np.array(model.g) > 0
    down = holding.equilibrium_curve(model, InputBounds([-P_MAX], [0.0]), np.array([0.5, 0.8]))
    assert np.all(down.inputs <= 0) and down.points[-1] @ np.array(model.g) < 0


@pytest.mark.timeout(180)
def test_a_one_input_finger_is_checked_along_the_curve_it_can_hold(monkeypatch):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    model = OneChamber()
    derived = ls.derive(model, _chamber_facts(), bandwidths=(2.0,), laws=('sdre_ff',))
    assert derived.settings is not None, derived.candidates
    facts = derived.facts
    path = np.asarray(facts.path)
    assert path.shape == (ls.PATH_POINTS, 2)
    # every waypoint is an equilibrium reached with at most half the chamber's range
    curve = holding.equilibrium_curve(model, facts.bounds, facts.unit)
    for p in path[1:]:
        k = np.argmin(np.linalg.norm(curve.points - p, axis=1))
        assert curve.inputs[k, 0] <= holding.HOLD_SHARE * P_MAX * 1.01
        assert np.linalg.norm(curve.points[k] - p) < 5e-5
    assert facts.travel <= facts.reach_travel
    check = derived.checks['sdre_ff']
    assert check.ok and check.rmse_rel <= ls.KEEP_NOMINAL and check.outside == 0
    assert check.rest_saturated == 0.0                   # resting at 0 Pa is not saturation
    # the parameter files' values: the controller's bounds, the trajectory node's close_path
    params = derived.params(['a', 'b'])
    assert params['controller']['input_lower'] == [0.0]
    assert params['controller']['input_upper'] == [P_MAX]
    assert 'torque_limit' not in params['controller']      # the bounds replace it
    plan = params['trajectory']
    waypoints = np.array(plan['close_path']).reshape(-1, 2)
    np.testing.assert_array_equal(waypoints, path[1:])
    assert plan['close_distance'] == facts.travel and 'side_distance' not in plan
    assert params['estimator']['task_dim'] == 2
    summary = derived.summary()
    assert summary['facts']['bounds'] == {'lower': [0.0], 'upper': [P_MAX]}
    assert len(summary['facts']['path']) == ls.PATH_POINTS


def test_a_straight_move_off_the_curve_is_never_the_one_checked():
    """Straight along +Y no pressure holds the chamber finger (its equilibria lie on the curve):
    the derivation plans along the curve whatever the data's direction (no bandwidth tried:
    only the move is made)."""
    model = OneChamber()
    derived = ls.derive(model, _chamber_facts(direction=90.0), bandwidths=())
    assert derived.settings is None and derived.facts.path is not None
    end = np.asarray(derived.facts.path[-1])
    u = holding.hold_torques(model, end[None])[0, 0]
    assert np.abs(model.statics(end, u)).max() < 1e-3 * model.g[0] * u        # on the curve
    u = holding.hold_torques(model, np.array([[0.0, 2e-3]]))
    free, G2 = holding.input_map(model, np.array([[0.0, 2e-3]]))
    assert np.linalg.norm(free[0] + G2[0] @ u[0]) > 1.0        # no input holds (0, 2 mm)


@pytest.mark.timeout(240)
def test_a_three_tendon_segment_is_checked_in_3d_within_its_pull_only_bounds(monkeypatch):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    model = ThreeTendons()
    derived = ls.derive(model, _tendon_facts(model), bandwidths=(2.0,))
    assert derived.settings is not None, derived.candidates
    for law, check in derived.checks.items():
        assert check.outside == 0, law                     # never a negative tension
    nominal = derived.checks['sdre_ff']
    assert nominal.ok and nominal.rmse_rel <= ls.KEEP_NOMINAL
    ref = ls.check_move(derived.facts)
    held = ref.sample(np.array([SHORT_PROFILE['t_start'] + SHORT_PROFILE['t_close']
                                + SHORT_PROFILE['t_hold'] / 2])).pos[0, 0]
    np.testing.assert_allclose(held, derived.facts.travel * derived.facts.unit, atol=1e-12)
    params = derived.params(['a', 'b'])
    assert params['estimator']['task_dim'] == 3 and params['trajectory']['task_dim'] == 3
    direction = params['trajectory']['direction']
    np.testing.assert_allclose(direction, derived.facts.unit)
    assert params['controller']['input_lower'] == [0.0] * 3
    # the hold inputs of the move are tendon 0 alone, within half its range
    u = holding.hold_torques(model, derived.facts.travel * derived.facts.unit[None])
    assert u[0, 0] <= holding.HOLD_SHARE * T_MAX and np.allclose(u[0, 1:], 0, atol=1e-12)
    # a free run from 3-D offsets comes back
    rest = mf.rest_stability(model, 1e-3, dt=2e-3)
    assert rest.stable and len(mf.rest_offsets(3)) == 14


def test_the_3d_move_is_cut_where_pull_only_tendons_cannot_hold_it():
    """Along −(tendon 0's direction) every tendon but 0 must push: nothing holds it."""
    model = ThreeTendons()
    facts = _tendon_facts(model)
    away = ls.DataFacts(**{**facts.__dict__, 'axis': tuple(-np.asarray(facts.axis))})
    assert holding.holdable_travel(model, away) == 0.0
    derived = ls.derive(model, away)
    assert derived.settings is None and 'excite with larger torques' in derived.reason
    assert 'input range' in derived.reason


def test_the_hand_shape_keeps_its_parameters():
    """A planar straight move with the symmetric limit: the trajectory node's close_distance and
    side_distance, no bounds, no task_dim; the rest pose the mean of a quarter second of tips
    (50 at 5 ms)."""
    facts = ls.DataFacts(period=5e-3, noise_std=5e-5, travel=2e-3, torque_limit=0.02,
                         accel_psd_ml=1.0, direction=120.0)
    settings = ls.settings_for(_Linear2(), facts, 2.0, 1.0)
    params = ls.Derivation(settings, {}, [], facts).params(['index', 'thumb'])
    assert list(params['trajectory']) == ['close_distance', 'side_distance', 'contact_distance',
                                          'rest_samples']
    assert params['trajectory']['rest_samples'] == 50
    assert 'task_dim' not in params['estimator'] and 'input_lower' not in params['controller']
    close, side = facts.move()
    assert params['trajectory']['close_distance'] == close
    assert 'axis' not in ls.Derivation(settings, {}, [], facts).summary()['facts']
    # no finger's fit with a lag took part: nothing expected of the fingers, nothing said
    assert 'on_fingers' not in ls.Derivation(settings, {}, [], facts).summary()
    assert ls.Derivation(settings, {}, [], facts).fingers_text() == ('', None)


def test_the_fingers_fits_expectation_is_said_and_a_miss_warned_naming_the_finger():
    """The chosen settings' runs on the fingers' fits are printed after training's verdict; a
    finger beyond KEEP_NOMINAL of the travel on its fit, or diverging there, is warned about by
    name."""
    facts = ls.DataFacts(period=1e-2, noise_std=5e-5, travel=3.7e-3, torque_limit=0.02,
                         accel_psd_ml=1.0)
    settings = ls.settings_for(_Linear2(), facts, 1.0, 1.0)

    def run(rmse, diverged=False):
        return {'rmse_rel': rmse, 'diverged': diverged}
    held = ls.Derivation(settings, {}, [], facts,
                         on_fingers={'index': run(0.0363), 'thumb': run(0.0344)})
    said, warning = held.fingers_text()
    assert said.startswith("on the fingers' own fits") and 'index 3.63 %, thumb 3.44 %' in said
    assert warning is None
    assert held.summary()['on_fingers'] == held.on_fingers
    missed = ls.Derivation(settings, {}, [], facts,
                           on_fingers={'index': run(0.087), 'thumb': run(0.03)})
    _, warning = missed.fingers_text()
    assert warning.startswith('WARNING') and 'index 8.70 %' in warning and 'thumb' not in warning
    assert f'{100 * ls.KEEP_NOMINAL:g} %' in warning
    ringing = ls.Derivation(settings, {}, [], facts,
                            on_fingers={'index': run(math.inf, True), 'thumb': run(0.02)})
    said, warning = ringing.fingers_text()
    assert 'index diverges' in said and 'index diverges' in warning


class _Linear2:
    rest_tip = np.zeros(3)

    def AG(self, x):
        n = len(np.atleast_2d(x))
        A = np.zeros((n, 4, 4))
        A[:, 0, 2] = A[:, 1, 3] = 1.0
        A[:, 2, 0] = A[:, 3, 1] = -400.0
        G = np.zeros((n, 4, 2))
        G[:, 2:, :] = [[300.0, 250.0], [-100.0, 200.0]]
        return A, G


def test_data_facts_in_3d_and_with_one_sided_inputs():
    rng = np.random.default_rng(1)
    u = rng.uniform(0.0, 2.0, (3000, 3))
    tips = u @ ThreeTendons().g2.T / ThreeTendons.k + rng.normal(0, 2e-5, (3000, 3))
    tune = [(np.arange(200) * 4e-3, tips[:200])]
    facts = df.data_facts(tips, u, 4e-3, 2e-5, tune, bounds=InputBounds(np.zeros(3),
                                                                         np.full(3, T_MAX)))
    assert facts.d == 3 and np.linalg.norm(facts.unit) == pytest.approx(1.0)
    assert facts.unit[1] > 0                                   # turned toward +Y
    np.testing.assert_allclose(facts.unit, df.principal_axis(tips))
    # 2 × the data's 2 N, within the tendons' 4 N, from their rest at 0
    np.testing.assert_allclose(facts.bounds.lower, 0.0)
    np.testing.assert_allclose(facts.bounds.upper, T_MAX, rtol=3e-3)
    tight = df.data_facts(tips, u, 4e-3, 2e-5, tune,
                          bounds=InputBounds(np.zeros(3), np.full(3, 2.5)))
    np.testing.assert_allclose(tight.bounds.upper, 2.5)
    assert tight.torque_limit == 2.5
    # inputs that act both ways keep the hand's rule: the symmetric limit, no bounds
    both = df.data_facts(tips, u - 1.0, 4e-3, 2e-5, tune,
                         bounds=InputBounds(np.full(3, -1.0), np.full(3, 1.0)))
    assert both.bounds is None
    assert both.torque_limit == pytest.approx(df.TORQUE_MARGIN * np.percentile(
        np.abs(u - 1.0).max(axis=1), 99.9))
    # ... unless the bounds are the actuators' (given): then never beyond them
    alike = df.input_range(u - 1.0, InputBounds(np.full(3, -1.5), np.full(3, 1.5)), given=True)
    assert alike == (1.5, None)
    uneven = df.input_range(u - 1.0, InputBounds([-1.5, -3.0, -1.2], [1.5, 3.0, 5.0]), given=True)
    np.testing.assert_allclose(uneven[1].lower, [-1.5, -both.torque_limit, -1.2])
    np.testing.assert_allclose(uneven[1].upper, [1.5, both.torque_limit, both.torque_limit])
    assert df.input_range(u - 1.0, InputBounds(np.full(3, -5.0), np.full(3, 5.0)),
                          given=True) == (both.torque_limit, None)
    # a pull-only input (acting toward −) rests at its upper bound
    lo, hi = df.input_range(-u[:, :1], InputBounds([-T_MAX], [0.0]))[1].lower, \
        df.input_range(-u[:, :1], InputBounds([-T_MAX], [0.0]))[1].upper
    assert hi[0] == 0.0 and lo[0] == pytest.approx(-T_MAX, rel=3e-3)


@pytest.mark.parametrize('make, message', [
    (lambda: ls.DataFacts(1e-3, 1e-5, 1e-3, 1.0, 1.0, axis=(1.0, 0.0, 0.0, 0.0)), 'axis'),
    (lambda: ls.DataFacts(1e-3, 1e-5, 1e-3, 1.0, 1.0, axis=(1.0, 1.0, 0.0)), 'unit vector'),
    (lambda: ls.DataFacts(1e-3, 1e-5, 1e-3, 1.0, 1.0, axis=(math.nan, 1.0)), 'axis'),
    (lambda: ls.DataFacts(1e-3, 1e-5, 1e-3, 1.0, 1.0, path=((0.0, 0.0, 0.0), (1.0, 0, 0))),
     'path'),
    (lambda: ls.DataFacts(1e-3, 1e-5, 1e-3, 1.0, 1.0, path=((0.0, 0.0),)), 'path'),
    (lambda: df.data_facts(np.zeros((10, 4)), np.zeros((10, 2)), 1e-3, 1e-5, []), 'got (10, 4)'),
    (lambda: df.input_range(np.ones((10, 2)), InputBounds([0.0], [1.0])),
     'input bounds: 1 input(s) recorded, the data hold 2'),
    (lambda: ls.derive(ThreeTendons(), _chamber_facts()), 'the move is 2-D'),
    (lambda: ls.derive(OneChamber(), ls.DataFacts(
        0.01, 2e-5, 6e-3, 1.0, 1.0, bounds=InputBounds([0.0, 0.0], [1.0, 1.0]))),
     'input bounds: 2 input(s)'),
    (lambda: ls.derive(OneChamber(), ls.DataFacts(0.0, 2e-5, 6e-3, 1.0, 1.0)),
     'DataFacts.period'),
    (lambda: ls.derive(OneChamber(), ls.DataFacts(0.01, -1.0, 6e-3, 1.0, 1.0)),
     'DataFacts.noise_std'),
    (lambda: ls.derive(OneChamber(), ls.DataFacts(0.01, 2e-5, 6e-3, math.inf, 1.0)),
     'DataFacts.torque_limit'),
    (lambda: holding.equilibrium_curve(OneChamber(), InputBounds([0.0, 0.0], [1.0, 1.0]),
                                       np.array([0.0, 1.0])), '2 input(s) for a model of 1'),
    (lambda: holding.equilibrium_curve(OneChamber(), InputBounds([0.0], [1.0]),
                                       np.array([0.0, 1.0, 0.0])), '3 values for a 2-D tip'),
])
def test_bad_values_are_refused_naming_them(make, message):
    with pytest.raises(ShapeError) as err:
        make()
    assert message in str(err.value)


def test_params_of_a_derivation_without_settings_say_why():
    facts = _chamber_facts()
    with pytest.raises(ValueError, match='no settings were derived: excite'):
        ls.Derivation(None, {}, [], facts, reason='excite with larger torques').params(['a'])


def test_the_in_process_loop_refuses_a_law_of_another_shape_than_its_simulator():
    """The in-process loop simulates the hand (d = 2, m = 2): a one-chamber law is refused
    before the simulator starts, naming both shapes."""
    from soft_gripper_sdre.analysis.closed_loop import law_shape, run_closed_loop
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import Weights
    law = make_law('sdre', OneChamber(), Weights(1.0, 0.0, 1.0), P_MAX, n_fingers=4,
                   bounds=InputBounds([0.0], [P_MAX]))
    assert law_shape(law) == FingerShape(2, 1)
    with pytest.raises(ShapeError, match=r'shape \(d=2, m=1\).*hand\'s \(d=2, m=2\)'):
        run_closed_loop(law, duration=0.1)
