"""The closed-loop check's plant steps a learned model compiled (analysis.model_fitness.CompiledRK4
inside analysis.loop_settings.ModelPlant): the same RK4 steps as numpy's to rounding on real SDC
models (the shipped hand's and short real trainings of other shapes), the same check numbers and
the same derived settings and rows as the numpy plant (:func:`close`); bad arguments refused naming
them."""
from dataclasses import asdict
import math

from chamber_models import SHORT_PROFILE, OneChamber
from known_systems import SYSTEMS, fit
import numpy as np
import pytest

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.analysis import model_fitness
from soft_gripper_sdre.analysis.model_fitness import CompiledRK4, rk4_step
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, SDCModel, set_blas_threads
from soft_gripper_sdre.learning.training import save_checkpoint
from soft_gripper_sdre.sim.shape import ShapeError


@pytest.fixture(scope='module')
def hand():
    set_blas_threads(1)           # as the training tool runs the checks (a 4 × 4 solve per step)
    return SDCModel(DEFAULT_MODEL)


@pytest.fixture(scope='module', params=[(2, 1), (3, 3)], ids=lambda s: f'd{s[0]}m{s[1]}')
def shaped(request, tmp_path_factory):
    """A learned model of another shape than the hand's: a short real training, saved and
    loaded as the tools load it."""
    d, m = request.param
    result, settings, _ = fit(d, m, epochs=5)
    path = tmp_path_factory.mktemp('compiled') / 'model.pt'
    save_checkpoint(path, result, rest_tip=np.zeros(3), dt=1e-3, settings=settings,
                    data={'source': 'test'}, input_bounds=SYSTEMS[(d, m)][1])
    return SDCModel(path)


def _states(model, n, seed):
    """n states (2d,) and inputs (m,) about the model's data scale."""
    shape = model.shape
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, shape.n_state)) * np.r_[[3e-3] * shape.d, [3e-2] * shape.d]
    u = rng.standard_normal((n, shape.m)) * 0.01
    return x, u


def _numpy_steps(model, x, u, dt, substeps):
    """The numpy RK4 the plant runs without compiling, for one state."""
    x = x[None].copy()
    for _ in range(substeps):
        x = rk4_step(model, x, u[None], dt / substeps)
    return x[0]


@pytest.mark.parametrize('substeps', [1, 3])
def test_the_compiled_steps_are_numpys_to_rounding(hand, shaped, substeps):
    for model in (hand, shaped):
        rk4 = CompiledRK4(model)
        x, u = _states(model, 20, seed=substeps)
        if model.input_bounds is not None:
            u = model.input_bounds.clip(u * 1e6)        # within a chamber's or tendon's range
        worst = 0.0
        moved = 0.0
        for xi, ui in zip(x, u):
            ref = _numpy_steps(model, xi, ui, 5e-3, substeps)
            got = xi.copy()
            rk4.step(got, ui, 5e-3, substeps)
            moved = max(moved, float(np.abs(got - xi).max()))
            worst = max(worst, float(np.abs(got - ref).max() / np.abs(ref).max()))
        assert moved > 0                                # the step did something
        assert worst < 1e-12


def close(a: float, b: float) -> None:
    """Two numbers of a check the same to rounding: within 1e-9 where the loop tracks; a loop
    that misses by more than :data:`~soft_gripper_sdre.analysis.loop_settings.KEEP_ROBUST` of the
    move rings, amplifying the rounding of the networks' sums (to some 1e-6 over a check), and
    only has to miss by as much on both."""
    if abs(b) <= ls.KEEP_ROBUST:
        assert a == pytest.approx(b, rel=1e-9, abs=1e-15)
    else:
        assert abs(a) > ls.KEEP_ROBUST and a == pytest.approx(b, rel=1e-3)


def _hand_facts(model, period=5e-3):
    return ls.DataFacts(period=period, noise_std=2e-5, travel=2e-3, torque_limit=0.02,
                        accel_psd_ml=1.0, direction=90.0)


@pytest.mark.parametrize('bandwidth', [4.0, 8.0])
def test_the_check_gives_the_numpy_plants_numbers(hand, monkeypatch, bandwidth):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    facts = _hand_facts(hand)
    settings = ls.settings_for(hand, facts, bandwidth, facts.accel_psd_ml)
    for gain in (1.0, *ls.GAIN_ERRORS):
        fast = ls.check_on_model(hand, settings, facts, gain_error=gain)
        assert ls.ModelPlant(hand, gain).rk4 is not None          # the check's default plant
        slow = ls.check_on_model(hand, settings, facts,
                                 plant=ls.ModelPlant(hand, gain, compiled=False))
        assert math.isfinite(fast.rmse_rel) and fast.rmse_rel > 0
        a, b = asdict(fast), asdict(slow)
        for key in ('rmse_rel', 'rest_torque'):
            close(a.pop(key), b.pop(key))
        assert a == b


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_derivation_chooses_what_the_numpy_plant_chooses(hand, monkeypatch):
    """The whole search with the compiled plant against the numpy plant's: the same settings,
    the same rows, every number within rounding (the numpy plant's search: 40 s to 2 min by the
    host and its load)."""
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    facts = _hand_facts(hand)
    fast = ls.derive(hand, facts, bandwidths=(4.0, 8.0), workers=1)

    class NumpyPlant(ls.ModelPlant):
        def __init__(self, model, gain_error=1.0):
            super().__init__(model, gain_error, compiled=False)
    monkeypatch.setattr(ls, 'ModelPlant', NumpyPlant)
    slow = ls.derive(hand, facts, bandwidths=(4.0, 8.0), workers=1)
    assert fast.settings is not None and fast.settings == slow.settings
    assert len(fast.candidates) == len(slow.candidates) >= 5

    def same(a, b):
        if isinstance(a, dict):
            assert a.keys() == b.keys()
            for key in a:
                same(a[key], b[key])
        elif isinstance(a, list):
            assert len(a) == len(b)
            for x, y in zip(a, b):
                same(x, y)
        elif isinstance(a, float) and math.isfinite(a):
            close(a, b)
        else:
            assert a == b
    same(fast.candidates, slow.candidates)
    same({k: asdict(v) for k, v in fast.checks.items()},
         {k: asdict(v) for k, v in slow.checks.items()})


def test_a_model_with_its_own_AG_keeps_numpys_steps():
    model = OneChamber()
    assert not CompiledRK4.fits(model)
    assert ls.ModelPlant(model).rk4 is None
    with pytest.raises(ValueError, match='CompiledRK4 needs a learned SDCModel.*OneChamber'):
        CompiledRK4(model)


@pytest.mark.parametrize('make, error, message', [
    (lambda: (np.zeros(3), np.zeros(2), 5e-3, 1), ShapeError, r'x must be a float64 array \(4,\)'),
    (lambda: (np.zeros(4), np.zeros(3), 5e-3, 1), ShapeError,
     r'and u \(2,\).*got \(4,\) and \(3,\)'),
    (lambda: (np.zeros(4, dtype=np.float32), np.zeros(2), 5e-3, 1), ShapeError, 'float64'),
    (lambda: ([0.0] * 4, np.zeros(2), 5e-3, 1), ShapeError, 'float64 array'),
    (lambda: (np.zeros(4), np.zeros(2), 5e-3, 0), ValueError, 'substeps must be an int >= 1'),
    (lambda: (np.zeros(4), np.zeros(2), 5e-3, 2.0), ValueError, 'got 2.0'),
    (lambda: (np.zeros(4), np.zeros(2), math.nan, 1), ValueError, 'dt finite and > 0'),
    (lambda: (np.zeros(4), np.zeros(2), -1e-3, 1), ValueError, 'got 1 and -0.001'),
])
def test_bad_step_arguments_are_refused_naming_them(hand, make, error, message):
    x, u, dt, substeps = make()
    with pytest.raises(error, match=message):
        CompiledRK4(hand).step(x, u, dt, substeps)


def test_a_diverging_state_stays_not_finite(hand):
    """A state that is not finite stays so (the check counts it as diverged), as numpy's."""
    x = np.array([math.nan, 0.0, 0.0, 0.0])
    CompiledRK4(hand).step(x, np.zeros(2), 5e-3, 2)
    assert not np.all(np.isfinite(x))
    assert not np.all(np.isfinite(_numpy_steps(hand, np.array([math.nan, 0.0, 0.0, 0.0]),
                                               np.zeros(2), 5e-3, 2)))


def test_the_gain_error_scales_the_input_map(hand):
    """ModelPlant(k) steps ẋ = A x + k G u compiled as in numpy."""
    for k in (0.5, 2.0):
        fast, slow = ls.ModelPlant(hand, k), ls.ModelPlant(hand, k, compiled=False)
        u = np.array([[0.01, -0.005]])
        for _ in range(5):
            fast.step(u, 5e-3)
            slow.step(u, 5e-3)
        assert np.abs(fast.tip() - fast.rest).max() > 1e-7
        np.testing.assert_allclose(fast.tip(), slow.tip(), rtol=0, atol=1e-15)


def test_a_compiled_run_is_simulates_to_rounding(hand, shaped):
    for model in (hand, shaped):
        shape = model.shape
        t = 5e-3 * np.arange(400)[:, None]
        wave = np.sin(2 * np.pi * (1.0 + np.arange(shape.m)) * t)          # smooth, one per input
        bounds = model.input_bounds
        u = 2e-3 * wave if bounds is None else bounds.mid + 0.5 * bounds.half_span * wave
        x0 = np.zeros(shape.n_state)
        ref = model_fitness.simulate(model, x0[None], u[:, None, :], 5e-3, substeps=2)[:, 0]
        got = CompiledRK4(model).simulate(x0, u, 5e-3, substeps=2)
        assert got.shape == ref.shape == (401, shape.n_state)
        assert np.isfinite(ref).all() and np.abs(ref[-1]).max() > 0
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-15 * np.abs(ref).max())
        # a run that leaves the bound is NaN from there on, as simulate's
        bound = 0.5 * np.abs(ref).max()
        ref = model_fitness.simulate(model, x0[None], u[:, None, :], 5e-3, 2, bound)[:, 0]
        got = CompiledRK4(model).simulate(x0, u, 5e-3, 2, bound)
        gone = ~np.isfinite(ref).all(axis=1)
        assert gone.any() and not gone[0]
        np.testing.assert_array_equal(~np.isfinite(got).all(axis=1), gone)


def test_the_unmodelled_delay_is_measured_as_with_numpys_run(shaped, monkeypatch):
    """unmodelled_delay runs a learned model compiled: the same delay as numpy's run."""
    shape, dt, late = shaped.shape, 5e-3, 4
    rng = np.random.default_rng(5)
    u = np.repeat(rng.random((60, shape.m)), 10, axis=0)           # steps held 50 ms
    u = shaped.input_bounds.lower + u * (shaped.input_bounds.upper - shaped.input_bounds.lower)
    run = model_fitness.simulate(shaped, np.zeros((1, shape.n_state)), u[:-1, None, :], dt,
                                 substeps=2)[:, 0, :shape.d]
    tips = np.concatenate([np.zeros((late, shape.d)), run[:-late]])   # the finger 4 periods late
    t = dt * np.arange(len(u))
    fast = ls.unmodelled_delay(shaped, t, u, tips)
    monkeypatch.setattr(CompiledRK4, 'fits', staticmethod(lambda model: False))
    slow = ls.unmodelled_delay(shaped, t, u, tips)
    assert fast == pytest.approx(slow, rel=1e-9)
    assert fast == pytest.approx(late * dt, abs=0.5 * dt)


@pytest.mark.parametrize('make, error, message', [
    (lambda: (np.zeros(3), np.zeros((5, 2)), 5e-3, 1, 1.0), ShapeError,
     r'x0 must be \(4,\) and u \(T, 2\).*got \(3,\) and \(5, 2\)'),
    (lambda: (np.zeros(4), np.zeros(5), 5e-3, 1, 1.0), ShapeError, r'got \(4,\) and \(5,\)'),
    (lambda: (np.zeros(4), np.zeros((5, 2)), 5e-3, 0, 1.0), ValueError,
     'substeps must be an int >= 1'),
    (lambda: (np.zeros(4), np.zeros((5, 2)), math.inf, 1, 1.0), ValueError, 'dt finite'),
    (lambda: (np.zeros(4), np.zeros((5, 2)), 5e-3, 1, 0.0), ValueError, 'bound > 0, got 1'),
])
def test_bad_run_arguments_are_refused_naming_them(hand, make, error, message):
    with pytest.raises(error, match=message):
        CompiledRK4(hand).simulate(*make())
