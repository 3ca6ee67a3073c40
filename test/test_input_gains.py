"""Each finger's input gain against the shared model (analysis/finger_fits.input_gains): read from
the recordings of fingers whose gains and dynamics are known, the bounds a law on the model runs
within so that every finger can deliver its command (InputBounds.through_gains), and the closed-loop
check, the fits and the parameter file that carry the gains."""
from dataclasses import replace
import math

from chamber_models import P_MAX, OneChamber, _chamber_facts, held_inputs
import numpy as np
import pytest

from soft_gripper_sdre.analysis import finger_fits as ff
from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.analysis.bag_dataset import FingerSamples
from soft_gripper_sdre.analysis.holding import equilibrium_curve, loop_bounds
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes.tracking_step import TrackingStep
from soft_gripper_sdre.sim.shape import HAND_SHAPE, INPUT_GAIN_RANGE, InputBounds, ShapeError

DT = 0.01


def _record(model, name: str, gain: float, inertia: float, damping: float, seconds: float,
            seed: int) -> FingerSamples:
    """A finger that is ``model`` with its input ``gain`` times as strong, ``inertia`` times as
    heavy and ``damping`` times as damped, driven by held pressures (RK4, exact labels)."""
    n = int(seconds / DT)
    u = held_inputs(n, 0.5 * P_MAX, seed, start=50)

    def acc(x, u):
        A, G = model.AG(x)
        a = A[0, 2:] @ x
        a[:2] = a[:2] - (damping - 1) * model.c * x[2:]
        return (a[:2] + gain * (G[0, 2:] @ u)) / inertia

    x, xs, accs = np.zeros(4), np.empty((n, 4)), np.empty((n, 2))
    for k in range(n):
        xs[k], accs[k] = x, acc(x, u[k])

        def f(z):
            return np.concatenate([z[2:], acc(z, u[k])])
        k1 = f(x)
        k2 = f(x + 0.5 * DT * k1)
        k3 = f(x + 0.5 * DT * k2)
        k4 = f(x + DT * k3)
        x = x + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return FingerSamples(f'b{seed}/{name}#0', np.arange(n) * DT, xs, u, accs)


def test_the_bounds_every_finger_delivers():
    both = InputBounds.symmetric(0.05, 2).through_gains([1.25, 0.8])
    np.testing.assert_allclose(both.upper, [0.04, 0.04])
    np.testing.assert_allclose(both.lower, [-0.04, -0.04])
    # one-sided: a chamber resting at 0 keeps its rest; the stronger finger's top goes unused
    pull = InputBounds([0.0, 0.0], [4.0, 6.0]).through_gains([1.1, 0.9, 1.0])
    np.testing.assert_allclose(pull.lower, [0.0, 0.0])
    np.testing.assert_allclose(pull.upper, [3.6, 5.4])
    for u in np.linspace(pull.lower, pull.upper, 7):        # every finger can deliver v / g
        for g in (1.1, 0.9, 1.0):
            assert InputBounds([0.0, 0.0], [4.0, 6.0]).contains(u / g, tol=1e-12)
    # bounds away from zero: the intersection, empty when the gains are too far apart
    np.testing.assert_allclose(InputBounds([1.0], [2.0]).through_gains([1.0, 1.5]).lower, [1.5])
    with pytest.raises(ShapeError, match=r'input ax0: no command within \[1, 2\]'):
        InputBounds([1.0], [2.0]).through_gains([1.0, 3.0])
    for bad in ([], [1.0, 0.0], [1.0, math.nan], [-1.0]):
        with pytest.raises(ShapeError, match='input gains must be finite and > 0'):
            InputBounds.symmetric(1.0).through_gains(bad)


def test_each_fingers_static_gain_is_read_though_its_dynamics_differ():
    """Two fingers of one model: the lighter, softer-damped one with 1.3 times the input gain,
    the heavier one with 0.8 times; read below STATIC_HZ, their gains come back within 2 %."""
    model = OneChamber()
    index = [_record(model, 'index', 1.3, 0.6, 0.5, 40.0, s) for s in (1, 2)]
    thumb = [_record(model, 'thumb', 0.8, 1.5, 1.0, 40.0, s) for s in (3, 4)]
    gains, missing = ff.input_gains(model, index + thumb)
    assert missing == [] and [g.name for g in gains] == ['index', 'thumb']
    assert gains[0].gain == pytest.approx(1.3, rel=0.02) and not gains[0].clipped
    assert gains[1].gain == pytest.approx(0.8, rel=0.02)
    assert gains[0].seconds == pytest.approx(2 * 39.99, abs=0.01)
    assert gains[0].summary() == {'finger': 'index', 'gain': gains[0].gain,
                                  'raw': gains[0].raw, 'seconds': gains[0].seconds,
                                  'clipped': False}


def test_a_finger_without_long_or_moving_recordings_has_no_gain_and_one_far_off_is_clipped():
    model = OneChamber()
    short = _record(model, 'index', 1.0, 1.0, 1.0, 1.0 / ff.STATIC_HZ - 0.5, 1)
    still = replace(_record(model, 'thumb', 1.0, 1.0, 1.0, 10.0, 2), u=np.zeros((1000, 1)))
    far = _record(model, 'ring', 3.0, 1.0, 1.0, 20.0, 3)
    gains, missing = ff.input_gains(model, [short, still, far])
    assert missing == ['index', 'thumb']
    assert gains[0].name == 'ring' and gains[0].clipped and gains[0].summary()['clipped']
    assert gains[0].gain == INPUT_GAIN_RANGE[1] and gains[0].raw == pytest.approx(3.0, rel=0.03)
    # a finger moving against the model's input map: clipped to the range's foot, flagged
    against = _record(model, 'pinky', -1.0, 1.0, 1.0, 20.0, 4)
    (back,), _ = ff.input_gains(model, [against])
    assert back.raw < 0 and back.clipped and back.gain == INPUT_GAIN_RANGE[0]
    # every finger the controller will drive is in the check's bounds: an unread one as the model
    by_finger = ff.gains_by_finger(gains, missing)
    assert by_finger == {'ring': 2.0, 'index': 1.0, 'thumb': 1.0}
    facts = _chamber_facts(input_gains=by_finger)
    assert loop_bounds(facts, 1) == InputBounds([0.0], [P_MAX])     # the unread ones at 1


def test_data_facts_refuse_bad_gains():
    for bad in ({}, {'index': 0.0}, {'index': math.inf}, {3: 1.0}, {'index': 'x'},
                {'index': True}):
        with pytest.raises(ShapeError, match='input gains must map finger names'):
            _chamber_facts(input_gains=bad)
    facts = _chamber_facts(input_gains={'index': 1, 'thumb': 0.8})
    assert facts.input_gains == {'index': 1.0, 'thumb': 0.8}
    assert loop_bounds(facts, 1) == InputBounds([0.0], [0.8 * P_MAX])


class Recorder(ls.ModelPlant):
    """The model as the check's plant, keeping every command it receives."""

    def __init__(self, model) -> None:
        super().__init__(model)
        self.commands = []

    def step(self, u, dt):
        self.commands.append(np.array(u, dtype=float).reshape(-1))
        super().step(u, dt)


def test_the_check_runs_the_law_within_what_every_finger_delivers():
    model = OneChamber()
    facts = _chamber_facts(travel=8e-3, input_gains={'index': 1.2, 'thumb': 0.7})
    settings = ls.settings_for(model, facts, 4.0, 1.0)
    plain = Recorder(model)
    ls.check_on_model(model, settings, replace(facts, input_gains=None), plant=plain)
    assert max(u.max() for u in plain.commands) > 0.75 * P_MAX     # it uses the whole range
    seen = Recorder(model)
    result = ls.check_on_model(model, settings, facts, plant=seen)
    assert result.outside == 0
    assert max(u.max() for u in seen.commands) <= 0.7 * P_MAX * (1 + 1e-12)


def test_a_fits_plant_receives_the_command_through_its_gain():
    K = np.array([[-380.0, 40.0, -3.0, 0.0], [30.0, -800.0, 0.0, -3.0]])
    fit = ff.LinearFinger('index', K, np.array([[2e-5], [1.2e-4]]), np.zeros(2), 0.05, 0.0, 0)
    strong, plain = (fit.plant(np.zeros(2), np.zeros(1), input_gain=g) for g in (2.0, 1.0))
    for k in range(50):
        u = np.array([[1e4 * (1 + k % 3)]])
        strong.step(u, DT)
        plain.step(u / 2.0, DT)
    np.testing.assert_allclose(strong.tip(), plain.tip(), rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match='input_gain must be finite and > 0'):
        fit.plant(np.zeros(2), np.zeros(1), input_gain=0.0)


def test_the_parameter_file_carries_each_fingers_gain_in_the_fingers_order():
    facts = _chamber_facts(input_gains={'thumb': 0.8, 'index': 1.2})
    settings = ls.settings_for(OneChamber(), facts, 2.0, 1.0)
    derived = ls.Derivation(settings, {}, [], facts)
    assert derived.params(['index', 'thumb'])['controller']['input_gains'] == [1.2, 0.8]
    assert derived.params(['index', 'ring'])['controller']['input_gains'] == [1.2, 1.0]
    assert derived.summary()['facts']['input_gains'] == {'thumb': 0.8, 'index': 1.2}
    assert 'input_gains' not in ls.Derivation(settings, {}, [], replace(
        facts, input_gains=None)).params(['index'])['controller']


class SnapThrough(OneChamber):
    """A chamber whose statics fold: along Y the spring is k (1 − 2.6 s + 1.8 s²) with s = y/b,
    always stiff, but k(y) y falls between s = 0.27 and 0.70, so under a rising pressure the
    equilibrium jumps ahead (about 0.65 b)."""

    b = 1e-3

    def AG(self, x):
        A, G = super().AG(x)
        s = np.atleast_2d(x)[:, 1] / self.b
        A[:, 3, 1] = -self.k[1] * (1 - 2.6 * s + 1.8 * s ** 2)
        return A, G


@pytest.mark.parametrize('b', [1e-3, 2e-3])
def test_the_equilibrium_curve_goes_on_past_a_fold_of_the_statics(b):
    """A snap of 0.65 or 1.3 mm: the longer one beyond the jump allowed between neighbouring
    points of a curve 0.5 mm long so far (1.05 mm), kept as it goes on the curve's way."""
    model = SnapThrough()
    model.b = b
    curve = equilibrium_curve(model, InputBounds([0.0], [P_MAX]), np.array([0.0, 1.0]))
    assert curve.inputs[-1, 0] == pytest.approx(P_MAX)          # to the bound
    assert curve.points[-1, 1] > 1.2 * model.b
    assert np.diff(curve.points[:, 1]).max() > 0.5 * model.b    # the jump past the fold
    for u, p in zip(curve.inputs, curve.points):                # every point an equilibrium
        A, G = model.AG(np.r_[p, 0.0, 0.0])
        np.testing.assert_allclose(A[0, 2:, :2] @ p + G[0, 2:, 0] * u[0], 0.0, atol=1e-6)


def test_a_tracking_step_with_gains_needs_the_actuators_bounds():
    model = SDCModel()
    with pytest.raises(ValueError, match='input_gains must be one finite gain > 0 per finger'):
        TrackingStep(model, ('a', 'b'), HAND_SHAPE, None, input_gains=[1.0, 1.1])
    for bad in ([1.0], [1.0, 0.0], [1.0, math.nan]):
        with pytest.raises(ValueError, match=r'per finger \(2\)'):
            TrackingStep(model, ('a', 'b'), HAND_SHAPE, InputBounds.symmetric(0.05),
                         input_gains=bad)
