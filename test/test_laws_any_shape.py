"""Every law on fingers of any shape (d tip coordinates, m inputs) and per-input bounds, closed
loop on synthetic SDC models of that shape (test/shaped_models.py): reachable references tracked,
commands finite and within bounds whatever the state, the unreachable demand of a one-input planar
tip reported and not chased, no wind-up against a one-sided bound, bad shapes and bounds refused."""
import numpy as np
import pytest
from shaped_models import REST, ShapedModel, input_signal, model_reference, rk4, track

from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.laws.feedforward import pseudo_inversion
from soft_gripper_sdre.control.laws.integral import ReachableIntegralAction
from soft_gripper_sdre.control.riccati import Check, sdre_gains
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import LawIO, Weights, hand_path, shape_of
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, InputBounds, ShapeError

W = Weights(1e6, 0.0, 1.6e4)
U_MAX = 0.05
DT = 1e-3
#: the shapes under test and their bounds: the hand's shape with one-sided inputs (chambers)
SHAPES = {(2, 1): InputBounds.symmetric(U_MAX, 1),
          (2, 2): InputBounds([0.0, 0.0], [U_MAX, U_MAX]),
          (3, 3): InputBounds.symmetric(U_MAX, 3),
          (3, 2): InputBounds.symmetric(U_MAX, 2),
          (2, 3): InputBounds([-U_MAX, 0.0, -U_MAX], [U_MAX, U_MAX, 0.5 * U_MAX]),
          (2, 4): InputBounds.symmetric(U_MAX, 4)}
SHAPE_IDS = [f'd{d}m{m}' for d, m in SHAPES]
#: PD gains for the synthetic models (the defaults are the hand's tuning)
PD = dict(pd_gains=dict(kp=4e3, kd=90.0))
LAWS = {'sdre': {}, 'sdre_ff': {}, 'computed_torque': {}, 'lqr': {}, 'pd': PD}


def law_for(name, shape, n_fingers=1, bounds=None, **options):
    model = ShapedModel(*shape)
    law = make_law(name, model, W, U_MAX, n_fingers=n_fingers, dt=DT,
                   bounds=SHAPES[shape] if bounds is None else bounds, **{**LAWS[name], **options})
    return law, model


@pytest.mark.parametrize('shape', SHAPES, ids=SHAPE_IDS)
@pytest.mark.parametrize('name', ['sdre_ff', 'computed_torque'])
def test_model_inversion_laws_track_a_reachable_reference(shape, name):
    """The model's own response to an input within the bounds is followed to within 1 % of its
    travel (the hold's error), inside the bounds, unsaturated, with no unreachable demand (a
    little where an input is missing: the model is inverted at x, not on the reference)."""
    law, model = law_for(name, shape)
    reference = model_reference(model, input_signal(SHAPES[shape], hz=1.0, level=0.15),
                                seconds=0.6, dt=DT)
    travel = np.abs(reference[0] - REST[:shape[0]]).max()
    errors, u, steps = track(law, model, reference, dt=DT)
    assert travel > 5e-3
    assert errors.max() < 0.01 * travel
    assert np.isfinite(u).all() and SHAPES[shape].contains(u)
    assert not any(s.saturated.any() for s in steps)
    assert u.shape == (len(errors), shape[1])
    demand = np.abs(reference[2]).max()
    missing_input = shape[1] < shape[0]
    assert max(s.unreachable[0] for s in steps) < (0.05 if missing_input else 1e-9) * demand


@pytest.mark.parametrize('shape', SHAPES, ids=SHAPE_IDS)
@pytest.mark.parametrize('name, tolerance', [('sdre', 0.1), ('lqr', 0.25), ('pd', 0.25)])
def test_feedback_laws_settle_at_a_reachable_set_point(shape, name, tolerance):
    """Started at rest, the tip settles near the equilibrium of a constant input within the bounds
    (the paper's law and the fixed-gain laws have no model inversion: a steady offset remains).
    Where one input serves a planar tip the offset may be three times larger and the second mode,
    which the input reaches only through the coupling, is lightly damped: the error is bounded
    over the last 0.1 s, not yet constant."""
    slack = 3.0 if shape[1] < shape[0] else 1.0
    law, model = law_for(name, shape)
    u_c = input_signal(SHAPES[shape], hz=1.0, level=0.3)(0.25)
    target = model_reference(model, lambda t: u_c, seconds=3.0, dt=DT)[0][-1]
    d = shape[0]
    steps = int(400 * slack) + 1
    set_point = (np.repeat(target[None], steps, 0), np.zeros((steps, d)), np.zeros((steps, d)))
    errors, u, _ = track(law, model, set_point, dt=DT, x0=np.zeros(2 * d))
    travel = np.linalg.norm(target - REST[:d])
    assert travel > 5e-3
    assert errors[-100:].max() < slack * tolerance * travel     # settled near the set point
    if shape[1] >= shape[0]:
        assert np.ptp(errors[-100:]) < 0.01 * travel
    assert np.isfinite(u).all() and SHAPES[shape].contains(u)


@pytest.mark.parametrize('shape', SHAPES, ids=SHAPE_IDS)
@pytest.mark.parametrize('name', [*LAWS, 'sdre_ff@ref', 'sdre@adaptive'])
def test_commands_are_finite_and_within_bounds_for_nan_states_and_singular_input_maps(shape, name):
    """Finger 0 is healthy, finger 1 has NaN estimates (and NaN acceleration), finger 2 sits where
    the model's G₂ is zero: every command stays finite and within the bounds, step after step."""
    law_name, _, option = name.partition('@')
    options = dict(ff_at='ref') if option == 'ref' else dict(adaptive=True) if option else {}
    bounds = SHAPES[shape]
    model = ShapedModel(*shape, dead_beyond=1e-3)
    law = make_law(law_name, model, W, U_MAX, n_fingers=3, dt=DT, bounds=bounds,
                   **{**LAWS[law_name], **options})
    d = shape[0]
    rng = np.random.default_rng(3)
    for k in range(12):
        pos = REST[:d] + rng.normal(0.0, 5e-4, (3, d))
        pos[2, 0] = REST[0] + 2e-3                              # G₂ = 0 here
        vel = rng.normal(0.0, 1e-2, (3, d))
        ref = REST[:d] + rng.normal(0.0, 2e-3, (3, d))
        acc = rng.normal(0.0, 1.0, (3, d))
        pos[1, k % d] = np.nan if k % 2 else np.inf
        acc[1] = np.nan
        step = law.compute(pos, vel, ref, np.zeros((3, d)), ref_acc=acc)
        assert step.u.shape == (3, shape[1])
        assert np.isfinite(step.u).all() and bounds.contains(step.u)
        assert np.isfinite(step.unreachable).all() and step.unreachable.shape == (3,)
        assert step.fallback[1] and not step.ok[1]
        if law_name != 'sdre_ff':       # sdre_ff's feedback solves at e = 0 (as the hand's does)
            assert step.failed_checks[1] & Check.NONFINITE
    if name in ('sdre_ff', 'computed_torque'):                   # the model inverted at x
        assert step.fallback[2]                                 # no inversion through G₂ = 0


PLANAR_ONE = (2, 1)


@pytest.mark.parametrize('name', [*LAWS])
def test_one_input_planar_tip_rests_unsaturated(name):
    """(d, m) = (2, 1) held at rest: zero input, nothing saturated, nothing unreachable."""
    law, _ = law_for(name, PLANAR_ONE, n_fingers=2)
    rest = np.repeat(REST[None, :2], 2, 0)
    for _ in range(20):
        step = law.compute(rest, np.zeros((2, 2)), rest, np.zeros((2, 2)),
                           ref_acc=np.zeros((2, 2)))
        np.testing.assert_array_equal(step.u, 0.0)
        assert not step.saturated.any() and not step.fallback.any()
        np.testing.assert_array_equal(step.unreachable, 0.0)


@pytest.mark.parametrize('name', ['sdre_ff', 'computed_torque'])
def test_one_input_planar_tip_reports_the_unreachable_demand_and_does_not_chase_it(name):
    """A reference across the one input's direction cannot be followed: the step reports the part
    of the demand outside G₂'s range, ‖(I − ĝĝᵀ) r‖, and the law does not drive the input into its
    bound chasing it; the integral holds only the reachable part of the error."""
    law, model = law_for(name, PLANAR_ONE, bounds=InputBounds.symmetric(1.0, 1))
    g = model.G2[:, 0] / np.linalg.norm(model.G2[:, 0])
    across = np.array([-g[1], g[0]])
    w = 2 * np.pi * 2.0
    amp = 5e-4
    errors, unreachable, saturated = [], [], []
    x = np.zeros(4)
    for k in range(400):
        t = k * DT
        p_d = REST[:2] + amp * np.sin(w * t) * across
        v_d = amp * w * np.cos(w * t) * across
        a_d = -amp * w * w * np.sin(w * t) * across
        step = law.compute((x[:2] + REST[:2])[None], x[None, 2:], p_d[None], v_d[None],
                           ref_acc=a_d[None])
        if k == 100 and name == 'sdre_ff':         # the demand the step inverted, at x
            A, _ = model.AG(x)
            r = a_d - A[0, 2:] @ np.concatenate([p_d - REST[:2], v_d])
            np.testing.assert_allclose(step.unreachable[0], np.linalg.norm(r - g * (g @ r)),
                                       rtol=1e-9)
        unreachable.append(step.unreachable[0])
        saturated.append(step.saturated.any())
        x = rk4(model, x, step.u[0], DT)
        errors.append(np.linalg.norm(x[:2] + REST[:2] - p_d))
    assert np.max(unreachable) > 0.1                 # m/s²: most of the demand is across g
    assert not any(saturated)
    assert np.isfinite(errors).all() and np.max(errors) < 3 * amp
    integral = getattr(law, 'integral', None)
    if integral is not None:
        np.testing.assert_allclose(integral.xi[0], g * (g @ integral.xi[0]), atol=1e-15)


def test_integral_does_not_wind_up_against_one_sided_bounds():
    """Chambers 0..p_max asked for a set point only negative pressure reaches: the inputs rest at
    their lower bound and the integral (band wide open, so only the anti-windup acts) stays
    frozen; back at a reachable reference the law recovers as fast as one without integral."""
    shape, bounds = (2, 2), SHAPES[(2, 2)]
    model = ShapedModel(*shape)
    wide = dict(integral_gain=1e5, integral_band=1.0)
    law = make_law('sdre_ff', model, W, U_MAX, n_fingers=1, dt=DT, bounds=bounds, **wide)
    plain = make_law('sdre_ff', model, W, U_MAX, n_fingers=1, dt=DT, bounds=bounds,
                     integral_gain=0.0)
    target = model_reference(model, lambda t: np.array([-0.01, -0.01]), seconds=3.0,
                             dt=DT)[0][-1]
    d = 2
    away = (np.repeat(target[None], 301, 0), np.zeros((301, d)), np.zeros((301, d)))
    e_away, u, steps = track(law, model, away, dt=DT, x0=np.zeros(4))
    assert np.isfinite(u).all() and bounds.contains(u)
    assert np.mean([s.saturated.any() for s in steps]) > 0.9          # pressed against 0
    np.testing.assert_array_less(np.abs(law.integral.torque()), 1e-3 * U_MAX)
    # had it integrated this error, ‖u_I‖ ≥ k_i ‖ξ‖ / σ_max(G₂): far beyond the inputs' range
    seconds = DT * len(e_away[100:])
    wound = 1e5 * e_away[100:].min() * seconds / np.linalg.norm(model.G2, 2)
    assert wound > 2 * U_MAX
    # the integral did not act: the law without one ends where this one does
    e_plain = track(plain, model, away, dt=DT, x0=np.zeros(4))[0]
    np.testing.assert_allclose(e_away, e_plain, rtol=1e-6)


def test_one_sided_input_holding_rest_under_noise_neither_chatters_nor_winds_up():
    """One chamber 0..p_max on a planar tip, holding rest under 20 µm estimate noise: the command
    stays at or above 0, small and smooth (the roll-off), the integral bounded near zero."""
    bounds = InputBounds([0.0], [U_MAX])
    model = ShapedModel(2, 1)
    law = make_law('sdre_ff', model, W, U_MAX, n_fingers=1, dt=DT, bounds=bounds)
    rest = (np.repeat(REST[None, :2], 1001, 0), np.zeros((1001, 2)), np.zeros((1001, 2)))
    errors, u, steps = track(law, model, rest, dt=DT, noise=2e-5, seed=1)
    assert bounds.contains(u) and np.isfinite(u).all()
    assert u.mean() < 0.05 * U_MAX and u.max() < 0.3 * U_MAX
    assert np.abs(np.diff(u[:, 0])).max() < 0.05 * U_MAX             # no bang-bang at the bound
    assert np.abs(law.integral.torque()).max() < 0.05 * U_MAX
    assert errors[-500:].mean() < 1e-4


@pytest.mark.parametrize('name', [*LAWS])
def test_the_general_path_on_the_hands_shape_gives_the_hands_torques(name):
    """Bounds ±u_max with one limit a hair apart take the general code (pseudo-inverses, scipy);
    where nothing saturates it gives the hand's code's torques."""
    model = ShapedModel(2, 2)
    hand = make_law(name, model, W, 1.0, n_fingers=2, dt=DT, method='reference', **LAWS[name])
    general = make_law(name, model, W, 1.0, n_fingers=2, dt=DT, **LAWS[name],
                       bounds=InputBounds([-1.0, -1.0 - 1e-9], [1.0, 1.0 + 1e-9]))
    assert hand.io.hand and not general.io.hand
    rng = np.random.default_rng(5)
    for _ in range(10):
        pos = REST[:2] + rng.normal(0, 1e-3, (2, 2))
        args = (pos, rng.normal(0, 1e-2, (2, 2)), REST[:2] + rng.normal(0, 1e-3, (2, 2)),
                rng.normal(0, 1e-2, (2, 2)))
        acc = rng.normal(0, 1.0, (2, 2))
        a, b = hand.compute(*args, ref_acc=acc), general.compute(*args, ref_acc=acc)
        assert not a.saturated.any()
        np.testing.assert_allclose(b.u, a.u, rtol=1e-7, atol=1e-12)


def test_the_one_rule_picks_the_hands_code_only_for_the_hands_shape_and_symmetric_bounds():
    sym = InputBounds.symmetric(U_MAX, 2)
    assert hand_path(HAND_SHAPE, sym)
    assert not hand_path(HAND_SHAPE, InputBounds([0.0, -U_MAX], [U_MAX, U_MAX]))
    assert not hand_path(HAND_SHAPE, InputBounds([-U_MAX, -0.02], [U_MAX, 0.02]))
    assert not hand_path(FingerShape(3, 2), InputBounds.symmetric(U_MAX, 2))
    fast = make_law('sdre_ff', ShapedModel(2, 2), W, U_MAX, n_fingers=1)
    assert fast.io.hand and fast.sdre.fast
    one_sided = make_law('sdre_ff', ShapedModel(2, 2), W, U_MAX, n_fingers=1,
                         bounds=SHAPES[(2, 2)])
    assert not one_sided.io.hand and not one_sided.sdre.fast
    assert make_law('sdre', ShapedModel(3, 3), W, U_MAX).sdre.shape == FingerShape(3, 3)


def test_sdre_gains_and_torques_for_a_3d_tip_are_the_riccati_equations():
    """SdreController for (d, m) = (3, 2): u = K x + K_s x_d with scipy's K, K_s (eq. 22-24)."""
    model = ShapedModel(3, 2)
    Q, R = W.Q(3), W.R(2)
    ctrl = SdreController(Q, R, 10.0, n=2, method='reference')
    rng = np.random.default_rng(2)
    x, xd = rng.normal(0, 1e-3, (2, 6)), rng.normal(0, 1e-3, (2, 6))
    A, G = model.AG(x)
    out = ctrl.step(A, G, x, xd)
    assert out.ok.all() and out.K.shape == (2, 2, 6) and out.P.shape == (2, 6, 6)
    for i in range(2):
        K, Ks, _ = sdre_gains(A[i], G[i], Q, R)
        np.testing.assert_allclose(out.u[i], K @ x[i] + Ks @ xd[i], rtol=1e-9)


def test_pseudo_inversion_is_exact_least_squares_or_minimum_norm():
    rng = np.random.default_rng(0)
    for d, m in ((2, 1), (3, 3), (2, 4), (3, 2)):
        A2, G2 = rng.normal(size=(3, d, 2 * d)), rng.normal(size=(3, d, m))
        xd, ad = rng.normal(size=(3, 2 * d)), rng.normal(size=(3, d))
        u, usable, unreachable = pseudo_inversion(A2, G2, xd, ad)
        assert usable.all()
        for i in range(3):
            r = ad[i] - A2[i] @ xd[i]
            np.testing.assert_allclose(u[i], np.linalg.lstsq(G2[i], r, rcond=None)[0],
                                       rtol=1e-9, atol=1e-12)
            # (where every input reaches, both are rounding: up to about 1e-12 on some CPUs)
            np.testing.assert_allclose(unreachable[i], np.linalg.norm(r - G2[i] @ u[i]),
                                       rtol=1e-9, atol=1e-10)
        if m >= d:
            np.testing.assert_allclose(unreachable, 0.0, atol=1e-10)
    G2 = np.zeros((2, 3, 3))
    G2[1] = np.diag([1.0, 1.0, 1e-12])                      # singular: no inversion
    G2[0] = np.eye(3)
    G2[0, 0, 0] = np.nan
    u, usable, unreachable = pseudo_inversion(np.zeros((2, 3, 6)), G2, np.zeros((2, 6)),
                                              np.ones((2, 3)))
    assert not usable.any() and np.all(u == 0.0)
    np.testing.assert_allclose(unreachable, [0.0, 1.0])     # NaN: nothing; singular: the z part


def test_shape_of_reads_the_shape_or_infers_it():
    class Shaped:
        shape = FingerShape(3, 1)
    assert shape_of(Shaped()) == FingerShape(3, 1)
    assert shape_of(ShapedModel(3, 2)) == FingerShape(3, 2)
    assert shape_of(ShapedModel(2, 4)) == FingerShape(2, 4)

    class Blocks:
        def sdc_blocks(self, x):
            return np.zeros((len(x), 3, 6)), np.zeros((len(x), 3, 1))
    assert shape_of(Blocks()) == FingerShape(3, 1)


def test_weights_of_any_shape_keep_the_hands():
    np.testing.assert_array_equal(W.Q, np.diag([1e6, 1e6, 0.0, 0.0]))
    np.testing.assert_array_equal(W.R, np.diag([1.6e4, 1.6e4]))
    np.testing.assert_array_equal(W.Q(3), np.diag([1e6] * 3 + [0.0] * 3))
    np.testing.assert_array_equal(W.R(1), [[1.6e4]])
    assert W.for_shape(FingerShape(2, 4))[1].shape == (4, 4)


# -- bad shapes and bounds -------------------------------------------------------------------
class NoShape:
    rest_tip = REST

    def AG(self, x):
        return np.zeros((1, 5, 5)), np.zeros((1, 5, 2))


class WrongShape:
    rest_tip = REST
    shape = (2, 2)


@pytest.mark.parametrize('call, error, match', [
    (lambda: make_law('sdre', ShapedModel(2, 1), W, U_MAX, bounds=InputBounds.symmetric(1, 2)),
     ShapeError, 'bounds: the model has 1 input'),
    (lambda: make_law('sdre_ff', ShapedModel(3, 3), W, U_MAX, bounds=(0.0, 1.0)),
     ShapeError, 'bounds must be InputBounds'),
    (lambda: make_law('koopman_lqr', ShapedModel(3, 3), W, U_MAX),
     ShapeError, "Koopman laws are the hand's"),
    (lambda: make_law('koopman_mpc', ShapedModel(2, 2), W, U_MAX, bounds=SHAPES[(2, 2)]),
     ShapeError, 'bounds ax0 \\[0, 0.05\\]'),
    (lambda: make_law('pd', NoShape(), W, U_MAX), ShapeError, 'cannot tell the shape'),
    (lambda: make_law('lqr', WrongShape(), W, U_MAX), ShapeError, 'model.shape must be'),
    (lambda: W.Q(4), ShapeError, 'task dimension d'),
    (lambda: W.R(5), ShapeError, 'number of inputs m'),
    (lambda: LawIO([0.01, 0.02], U_MAX, 1, 0.0, DT, FingerShape(3, 3)), ValueError,
     'rest_tip must hold a finite rest position of 3'),
    (lambda: make_law('sdre', ShapedModel(3, 3), W, U_MAX, n_fingers=1).compute(
        *[np.zeros((1, 2))] * 4), ValueError, r'must each have shape \(1, 3\)'),
    (lambda: make_law('sdre_ff', ShapedModel(3, 2), W, U_MAX, n_fingers=1).compute(
        *[np.zeros((1, 3))] * 4, ref_acc=np.zeros((1, 2))), ValueError,
     r'ref_acc must have shape \(1, 3\)'),
    (lambda: SdreController(np.eye(5), np.eye(2), 1.0), ValueError, 'Q must be a finite'),
    (lambda: SdreController(np.eye(6), np.eye(5), 1.0), ValueError, 'R must be a finite'),
    (lambda: SdreController(np.eye(6), np.eye(3), [1.0, 2.0]), ValueError, 'one limit per input'),
    (lambda: SdreController(np.eye(6), np.eye(3), 1.0, bounds=InputBounds.symmetric(1, 2)),
     ShapeError, 'bounds: the model has 3'),
    (lambda: ReachableIntegralAction(np.zeros((2, 1)), 1.0, 1e-3, InputBounds.symmetric(1, 1),
                                     1, DT), ValueError, 'g2_rest must be'),
    (lambda: ReachableIntegralAction(np.ones((2, 2)), 1.0, 1e-3, InputBounds.symmetric(1, 1),
                                     1, DT), ValueError, 'g2_rest must be'),
    (lambda: ConstantVelocityKF(1e-3, 1.0, 1e-4, d=4), ShapeError, 'task dimension d'),
    (lambda: ConstantVelocityKF(1e-3, 1.0, 1e-4, n=1, d=3).step(np.zeros((1, 2))), ValueError,
     r'z must have shape \(1, 3\)'),
    (lambda: ConstantVelocityKF(1e-3, 1.0, 1e-4, n=1, d=3).step(np.zeros((1, 3)), dt=-1.0),
     ValueError, 'dt must be finite'),
])
def test_bad_shapes_and_bounds_are_refused_by_name(call, error, match):
    with pytest.raises(error, match=match):
        call()


# -- the Kalman filter for a 3-D tip ---------------------------------------------------------
@pytest.mark.parametrize('process_noise', ['independent', 'paper'])
def test_kf_for_a_3d_tip(process_noise):
    """Independent axes: a 3-D filter's X, Y are the planar filter's (the compiled one) on the same
    X, Y; the paper's coupled noise runs too; invalid or non-finite rows only predict."""
    rng = np.random.default_rng(1)
    kf3 = ConstantVelocityKF(1e-3, 4.0, 5e-5, n=2, process_noise=process_noise, d=3)
    kf2 = ConstantVelocityKF(1e-3, 4.0, 5e-5, n=2, process_noise=process_noise)
    assert kf3.x.shape == (2, 6) and kf3.P.shape == (2, 6, 6)
    for k in range(200):
        z = np.cumsum(rng.normal(0, 1e-4, (2, 3)), axis=0)
        dt = 1e-3 if k % 3 else 1.7e-3
        valid = np.array([True, k % 5 != 0])
        a, b = kf3.step(z, valid, dt=dt), kf2.step(z[:, :2], valid, dt=dt)
        if process_noise == 'independent':
            np.testing.assert_allclose(a[:, [0, 1, 3, 4]], b, rtol=1e-9, atol=1e-15)
        assert np.isfinite(a).all()
    x = kf3.x.copy()
    kf3.step(np.full((2, 3), np.nan))
    np.testing.assert_allclose(kf3.x[:, :3], x[:, :3] + 1e-3 * x[:, 3:], rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(kf3.P) > 0)


def test_oracle_laws_refuse_bounds_other_than_the_simulated_hands():
    from soft_gripper_sdre.analysis.oracle import register_oracle_laws
    register_oracle_laws()
    with pytest.raises(ShapeError, match="oracle laws are the simulated hand's"):
        make_law('oracle_ff', ShapedModel(2, 2), W, U_MAX, bounds=SHAPES[(2, 2)])


def test_symmetric_bounds_for_the_hand_are_the_hands_law_and_hand_over_keeps_the_integral():
    """Bounds ±u_max on the hand's shape give the law bounds=None gives, bit for bit; on the
    general path hand_over carries the reachable integral's torque to a law of another gain."""
    from soft_gripper_sdre.control.laws import hand_over
    model = ShapedModel(2, 2)
    plain = make_law('sdre_ff', model, W, U_MAX, n_fingers=2, dt=DT)
    bounded = make_law('sdre_ff', model, W, 0.01, n_fingers=2, dt=DT,
                       bounds=InputBounds.symmetric(U_MAX, 2))
    assert bounded.io.hand and bounded.io.u_max == U_MAX
    rng = np.random.default_rng(4)
    saturated = False
    for _ in range(5):
        args = [REST[:2] + rng.normal(0, 1e-3, (2, 2)), rng.normal(0, 1e-2, (2, 2)),
                REST[:2] + rng.normal(0, 1e-2, (2, 2)), rng.normal(0, 1e-2, (2, 2))]
        a, b = plain.compute(*args), bounded.compute(*args)
        np.testing.assert_array_equal(a.u, b.u)
        saturated |= a.saturated.any()
    assert saturated                                  # the bounds' limit, not u_max, in force
    bounds = SHAPES[(3, 2)]
    old, new = (make_law('sdre_ff', ShapedModel(3, 2), W, U_MAX, n_fingers=1, dt=DT,
                         bounds=bounds, integral_gain=k, integral_band=1.0) for k in (1e5, 4e5))
    for _ in range(50):
        old.compute(REST[None, :3] + 1e-4, np.zeros((1, 3)), REST[None, :3], np.zeros((1, 3)))
    assert np.abs(old.integral.torque()).max() > 1e-5
    hand_over(old, new)
    np.testing.assert_allclose(new.integral.torque(), old.integral.torque(), rtol=1e-12)


def test_the_general_fast_path_warm_starts_and_gives_the_reference_torques():
    """Off the hand's path 'fast' takes Newton–Kleinman from each finger's last solution (scipy
    only for the first step; a warm start that fails a check is solved again from scratch in the
    kernel) and gives scipy's torques."""
    model = ShapedModel(3, 2)
    fast, ref = (make_law('sdre', model, W, U_MAX, n_fingers=2, dt=DT, method=m,
                          bounds=SHAPES[(3, 2)]) for m in ('fast', 'reference'))
    rng = np.random.default_rng(8)
    for k in range(30):
        args = [REST[:3] + rng.normal(0, 2e-3, (2, 3)), rng.normal(0, 2e-2, (2, 3)),
                REST[:3] + rng.normal(0, 2e-3, (2, 3)), np.zeros((2, 3))]
        a, b = fast.compute(*args), ref.compute(*args)
        assert a.ok.all() and b.ok.all()
        np.testing.assert_allclose(a.u_unsat, b.u_unsat, rtol=1e-6, atol=1e-12)
        if k == 10:                                   # a warm start that cannot converge
            fast.sdre.state.P[0] = -np.eye(6)
    assert fast.sdre.exact_solves == 2 and ref.sdre.exact_solves == 60
