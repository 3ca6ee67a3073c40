"""The closed-loop check's steps run compiled (control.kernels.check_loop, driven by
analysis.loop_settings.check_on_model) where the loop allows it: the default law on the hand's path
with its integral action, on the learned model or on a finger's linear fit. Its results are the
Python loop's: the same CheckResult on the model, to rounding on a linear fit (numba's and numpy's
matrix products), with steps handed back to the law's scipy path mid-run; it runs most of the
steps; and every other loop (another law, bounded inputs, any other plant) stays in Python."""
from dataclasses import asdict
import math

from chamber_models import SHORT_PROFILE, OneChamber, _chamber_facts
import numpy as np
import pytest

from soft_gripper_sdre.analysis import finger_fits as ff
from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, SDCModel, set_blas_threads


@pytest.fixture(scope='module')
def hand():
    set_blas_threads(1)           # as the training tool runs the checks (a 4 × 4 solve per step)
    return SDCModel(DEFAULT_MODEL)


@pytest.fixture
def short(monkeypatch):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)


class Calls:
    """``ls.feedforward_check_steps`` wrapped: the steps each call ran, and whether it said the
    run diverged."""

    def __init__(self, monkeypatch) -> None:
        self.ran, self.left = [], []
        kernel = ls.feedforward_check_steps

        def counted(k, *args):
            end, left = kernel(k, *args)
            self.ran.append(end - k)
            self.left.append(left)
            return end, left
        monkeypatch.setattr(ls, 'feedforward_check_steps', counted)


def python_only(monkeypatch) -> None:
    monkeypatch.setattr(ls._CompiledSteps, 'of', classmethod(lambda cls, *args: None))


def _facts(period=5e-3):
    return ls.DataFacts(period=period, noise_std=2e-5, travel=2e-3, torque_limit=0.02,
                        accel_psd_ml=1.0, direction=90.0)


def _check(model, settings, facts, monkeypatch, **kw):
    """(compiled, python, the kernel's calls) of one check."""
    calls = Calls(monkeypatch)
    fast = ls.check_on_model(model, settings, facts, **kw)
    with monkeypatch.context() as m:
        python_only(m)
        slow = ls.check_on_model(model, settings, facts, **kw)
    return fast, slow, calls


@pytest.mark.parametrize('bandwidth, period, gain', [(4.0, 5e-3, 1.0), (8.0, 5e-3, 0.5),
                                                     (8.0, 2e-3, 2.0), (30.0, 2e-3, 1.0)])
def test_the_compiled_steps_give_the_python_loops_result(hand, short, monkeypatch, bandwidth,
                                                         period, gain):
    facts = _facts(period)
    settings = ls.settings_for(hand, facts, bandwidth, facts.accel_psd_ml)
    fast, slow, calls = _check(hand, settings, facts, monkeypatch, gain_error=gain)
    assert fast == slow and not fast.diverged
    ran = calls.ran
    steps = round(sum(SHORT_PROFILE.values()) / period) + 1
    assert ran and sum(ran) >= 0.9 * (steps - 1)      # all but the first (cold) step, or nearly


def test_a_diverging_run_stops_where_the_python_loop_stops(hand, short, monkeypatch):
    """A loop too fast for its period (16 Hz at 5 ms): the compiled run leaves the bound and
    says so."""
    facts = _facts(5e-3)
    settings = ls.settings_for(hand, facts, 16.0, facts.accel_psd_ml)
    fast, slow, calls = _check(hand, settings, facts, monkeypatch)
    assert fast == slow and fast.diverged and fast.rmse_rel == math.inf
    assert calls.left[-1]


def test_steps_handed_back_to_the_exact_path_run_there_and_the_loop_goes_on(hand, short,
                                                                           monkeypatch):
    """The checks' largest condition number held to 1.6, inside the range this run's take (every
    step passes at 1.7, none at 1.5): on the steps above it the kernel leaves the finger cold,
    each such step is undone in the kernel and run by the law (its fallback, then scipy), and the
    compiled steps resume: the same result as the Python loop's."""
    make_law = ls.make_law

    def tight(*args, **kw):
        law = make_law(*args, **kw)
        law.sdre.settings.cond_max[0] = 1.6
        return law
    monkeypatch.setattr(ls, 'make_law', tight)
    facts = _facts(5e-3)
    settings = ls.settings_for(hand, facts, 8.0, facts.accel_psd_ml)
    fast, slow, calls = _check(hand, settings, facts, monkeypatch)
    assert fast == slow and not fast.diverged
    assert len(calls.ran) > 10 and sum(calls.ran) > 10      # handed back often, resumed each time


def _lagged_fit(model, lag=0.03) -> ff.LinearFinger:
    """The model's linearisation at rest as a finger's linear fit, with an input lag."""
    A, G = model.AG(np.zeros((1, 4)))
    return ff.LinearFinger('index', A[0, 2:, :], G[0, 2:, :], np.zeros(2), lag, 0.0, 0)


@pytest.mark.parametrize('input_gain', [1.0, 1.3])
def test_a_fingers_linear_fit_as_the_plant_gives_the_python_loops_numbers(hand, short,
                                                                         monkeypatch,
                                                                         input_gain):
    facts = _facts(5e-3)
    settings = ls.settings_for(hand, facts, 4.0, facts.accel_psd_ml)
    fit = _lagged_fit(hand)

    def plant():
        return fit.plant(np.asarray(hand.rest_tip, float), np.zeros(2), input_gain=input_gain)
    calls = Calls(monkeypatch)
    fast = ls.check_on_model(hand, settings, facts, plant=plant())
    python_only(monkeypatch)
    slow = ls.check_on_model(hand, settings, facts, plant=plant())
    assert calls.ran and math.isfinite(fast.rmse_rel)
    a, b = asdict(fast), asdict(slow)
    for key in ('rmse_rel', 'rest_torque'):
        assert a.pop(key) == pytest.approx(b.pop(key), rel=1e-9, abs=1e-15)
    assert a == b


def test_other_loops_stay_in_python(hand, short, monkeypatch):
    """The paper's law, a plant of the caller's and a one-chamber finger's bounded input run the
    Python loop (the kernel is never called)."""
    calls = Calls(monkeypatch)
    facts = _facts(5e-3)
    settings = ls.settings_for(hand, facts, 4.0, facts.accel_psd_ml)
    assert math.isfinite(ls.check_on_model(hand, settings, facts, law='sdre').rmse_rel)

    class Own(ls.ModelPlant):
        """The model as a plant of the caller's (not the check's own class)."""
    own = ls.check_on_model(hand, settings, facts, plant=Own(hand))
    assert calls.ran == []
    assert own == ls.check_on_model(hand, settings, facts)
    assert calls.ran
    calls.ran.clear()
    chamber, chamber_facts = OneChamber(), _chamber_facts(travel=2e-3)
    ls.check_on_model(chamber, ls.settings_for(chamber, chamber_facts, 2.0, 1.0), chamber_facts)
    assert calls.ran == []
