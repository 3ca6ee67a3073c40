"""The controller's law from its parameters and its runtime retuning (nodes/law_tuning.py), and
one answered estimate to one torque (nodes/tracking_step.py), without DDS."""
import numpy as np
import pytest

from soft_gripper_sdre.control.command_gate import Plan
from soft_gripper_sdre.control.horizon import sample_plan
from soft_gripper_sdre.control.laws import DEFAULT_PD
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes.controller import PARAMS
from soft_gripper_sdre.nodes.law_tuning import LawTuning
from soft_gripper_sdre.nodes.tracking_step import TrackingStep

MODEL = SDCModel()
DEFAULTS = {p.name: p.default for p in PARAMS}
MS = 1_000_000


def tuning(**params) -> LawTuning:
    return LawTuning(MODEL, 4, {**DEFAULTS, **params})


def test_the_law_is_built_from_the_parameters_it_reads():
    t = tuning(law='pd', pd_kp=2e4)
    assert (t.law.kp, t.law.kd) == (2e4, DEFAULT_PD['kd'])      # kd 0: the law's own
    assert t.uses('pd_kp') and not t.uses('q_pos') and not t.uses('integral_gain')
    assert t.shown()['pd_gains'] == f'kp=20000 kd={DEFAULT_PD["kd"]:g}'
    with pytest.raises(ValueError):
        tuning(r=0.0)                                   # R must be > 0


def test_a_refused_change_keeps_the_law_and_its_values():
    t = tuning()
    law, shown = t.law, t.shown()
    reason = t.check({'r': 0.0, 'q_pos': 2e6})
    assert reason.startswith('q_pos, r: ')
    assert t.law is law and t.shown() == shown


def test_an_accepted_change_hands_the_law_over_and_an_unused_one_is_taken_without_effect():
    t = tuning()
    law = t.law
    assert t.check({'integral_gain': 2e5}) is None
    assert t.apply({'integral_gain': 2e5}) == (
        'integral_gain = 200000: the sdre_ff law is retuned from the next estimate')
    assert t.law is not law and t.law.integral.gain == 2e5
    assert t.shown()['integral'].startswith('gain=200000 ')
    law = t.law
    assert t.check({'pd_kd': 5.0, 'estimate_watchdog': 1.0}) is None
    assert t.apply({'pd_kd': 5.0, 'estimate_watchdog': 1.0}) == (
        'pd_kd = 5: not used by the sdre_ff law, no effect')
    assert t.law is law and t.shown()['pd_gains'].endswith(' kd=5')
    assert t.check({'estimate_watchdog': 1.0}) is None
    assert t.apply({'estimate_watchdog': 1.0}) is None


class Shifted:
    """The two attributes rest_shift reads: finger b rests 1 mm right of the model's rest."""

    rest_tip = MODEL.rest_tip
    finger_rests = {'a': MODEL.rest_tip, 'b': MODEL.rest_tip - [1e-3, 0.0, 0.0]}


class Echo:
    """A law whose torque is the tip position it is given (NaN where ``bad``)."""

    def __init__(self, bad: bool = False) -> None:
        self.bad, self.refs = bad, []

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None):
        self.refs.append(ref_pos)
        u = np.full_like(pos, np.nan) if self.bad else pos.copy()
        return type('Step', (), {'u': u})()


def plan(n: int) -> Plan:
    times = np.array([0, 10 * MS], dtype=np.int64)
    pos = np.linspace(0.0, 1e-3, 2 * n * 2).reshape(2, n, 2)
    vel, acc = np.ones((2, n, 2)) * 1e-2, np.zeros((2, n, 2))
    return Plan(0, 10 * MS, times, pos, vel, acc)


def test_the_step_samples_the_plan_shifts_each_finger_into_the_models_frame_and_times_the_law():
    step, p, law = TrackingStep(Shifted(), ('a', 'b')), plan(2), Echo()
    x = np.zeros((2, 4))
    command = step.command(law, 3 * MS, x, p)
    expected = sample_plan(p.times, p.pos, p.vel, p.acc, 3 * MS, with_acc=True)
    for got, want in zip(step.sample(p, 3 * MS), expected):
        np.testing.assert_array_equal(got, want)
    shift = np.array([[0.0, 0.0], [1e-3, 0.0]])
    np.testing.assert_array_equal(command.u, shift)
    np.testing.assert_array_equal(law.refs[0], expected[0] + shift)
    assert not command.replaced
    mean, peak = step.take_compute_us()
    assert 0 <= mean <= peak and step.take_compute_us() is None


def test_a_torque_that_is_not_finite_becomes_zero():
    step = TrackingStep(MODEL, ('finger_0',))
    command = step.command(Echo(bad=True), 0, np.zeros((1, 4)), plan(1))
    assert command.replaced and np.all(command.u == 0.0) and np.isnan(command.out.u).all()
