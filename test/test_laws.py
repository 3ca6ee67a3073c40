"""The laws (soft_gripper_sdre.control.laws, and the oracles of analysis.oracle) against closed
forms."""
from types import SimpleNamespace

import numpy as np
import pytest
from sdc_models import REST, StiffeningModel, sine_reference, track_sine

from soft_gripper_sdre.analysis.oracle import (
    ORACLE_LAWS,
    OracleFeedforwardLaw,
    OracleSdreLaw,
    register_oracle_laws,
)
from soft_gripper_sdre.control.laws import (
    GRAPH_LAWS,
    LAW_REGISTRY,
    AdaptiveSdreLaw,
    LqrLaw,
    PdLaw,
    SdreFeedforwardLaw,
    SdreLaw,
    make_law,
)
from soft_gripper_sdre.control.riccati import sdre_gains
from soft_gripper_sdre.control.tracking import Weights


class LinearModel:
    """ẍ = A21 p + A22 v + G2 u with constant matrices (a model with the SDCModel interface)."""

    def __init__(self, A21=np.zeros((2, 2)), G2=np.eye(2)):
        self.rest_tip = REST
        self._A = np.zeros((4, 4))
        self._A[0, 2] = self._A[1, 3] = 1.0
        self._A[2:, :2] = A21
        self._G = np.zeros((4, 2))
        self._G[2:] = G2

    def AG(self, x):
        x = np.atleast_2d(x)
        n = x.shape[0]
        return (np.broadcast_to(self._A, (n, 4, 4)).copy(),
                np.broadcast_to(self._G, (n, 4, 2)).copy())


def test_lqr_gain_of_the_double_integrator_is_the_closed_form():
    """ẍ = u per axis, Q = diag(q, q, 0, 0), R = r I: K = −[√(q/r), √(2√(q/r))] per axis."""
    q, r = 4.0e6, 1.0e2
    law = LqrLaw(LinearModel(), Weights(q, 0.0, r), u_max=1e9, n_fingers=1, lowpass_hz=0.0)
    k1, k2 = np.sqrt(q / r), np.sqrt(2 * np.sqrt(q / r))
    np.testing.assert_allclose(law.K, -np.array([[k1, 0, k2, 0], [0, k1, 0, k2]]), rtol=1e-8)


def test_lqr_law_applies_its_frozen_gains_in_translated_coordinates():
    model = LinearModel(A21=-np.diag([300.0, 900.0]), G2=np.array([[10.0, 600.0], [-600.0, 5.0]]))
    w = Weights(1e6, 0.0, 1.6e4)
    law = LqrLaw(model, w, u_max=1e9, n_fingers=2, lowpass_hz=0.0)
    pos = REST[:2] + np.array([[1e-3, -2e-3], [0.0, 5e-4]])
    vel = np.array([[0.01, 0.0], [0.0, -0.02]])
    ref = REST[:2] + np.array([[0.0, 1e-3], [2e-3, 0.0]])
    ref_vel = np.zeros((2, 2))
    out = law.compute(pos, vel, ref, ref_vel)
    x = np.hstack([pos - REST[:2], vel])
    xd = np.hstack([ref - REST[:2], ref_vel])
    np.testing.assert_allclose(out.u, x @ law.K.T + xd @ law.Ks.T, rtol=1e-12)
    # the same gains as the SDRE controller on the same (state-independent) model
    sdre = SdreLaw(model, w, 1e9, n_fingers=2, method='reference', lowpass_hz=0.0)
    np.testing.assert_allclose(sdre.compute(pos, vel, ref, ref_vel).u, out.u, rtol=1e-6)


def test_pd_law_is_the_inverse_input_map_times_the_pd_acceleration():
    G2 = np.array([[15.0, 640.0], [-620.0, -8.0]])
    law = PdLaw(LinearModel(G2=G2), u_max=1e9, kp=2000.0, kd=30.0, n_fingers=1, lowpass_hz=0.0)
    pos, vel = REST[None, :2] + [[1e-3, 0.0]], np.array([[0.0, 0.02]])
    ref, ref_vel = REST[None, :2] + [[0.0, 3e-3]], np.array([[0.01, 0.0]])
    a = 2000.0 * (ref - pos) + 30.0 * (ref_vel - vel)
    out = law.compute(pos, vel, ref, ref_vel)
    np.testing.assert_allclose(G2 @ out.u[0], a[0], rtol=1e-10)
    assert out.ok.all() and not out.fallback.any() and not out.saturated.any()


def test_laws_saturate_roll_off_and_refuse_non_finite_states():
    law = PdLaw(LinearModel(), u_max=0.05, kp=1e4, kd=0.0, n_fingers=2, lowpass_hz=40.0, dt=1e-3)
    pos = REST[None, :2].repeat(2, 0)
    ref = pos + [[1.0, 0.0], [np.nan, 0.0]]
    out = law.compute(pos, np.zeros((2, 2)), ref, np.zeros((2, 2)))
    assert out.saturated[0, 0] and not out.ok[1] and out.fallback[1]
    np.testing.assert_array_equal(out.u[1], [0.0, 0.0])        # no torque from a NaN reference
    np.testing.assert_allclose(out.u[0], [0.05, 0.0])          # first step: the filter starts there
    out = law.compute(pos, np.zeros((2, 2)), pos, np.zeros((2, 2)))
    a = np.exp(-2 * np.pi * 40.0 * 1e-3)
    np.testing.assert_allclose(out.u[0], [a * 0.05, 0.0])      # u_k = a u_{k−1} + (1 − a) · 0
    law.reset()
    assert np.all(law.compute(pos, np.zeros((2, 2)), pos, np.zeros((2, 2))).u == 0.0)


def test_make_law_names_and_options():
    model, w = LinearModel(), Weights(1e6, 0.0, 1.6e4)
    assert type(make_law('sdre', model, w, 0.06)) is SdreLaw
    assert isinstance(make_law('sdre', model, w, 0.06, adaptive=True), AdaptiveSdreLaw)
    assert isinstance(make_law('lqr', model, w, 0.06), LqrLaw)
    assert isinstance(make_law('pd', model, w, 0.06), PdLaw)
    with pytest.raises(ValueError, match='unknown law .*known'):
        make_law('mpc', model, w, 0.06)
    with pytest.raises(ValueError, match=r"adaptive=True \(state-dependent weights Q\(x\)\) is "
                                         r"not an option of the 'pd' law.*'sdre'"):
        make_law('pd', model, w, 0.06, adaptive=True)
    with pytest.raises(ValueError, match='not an option'):
        make_law('sdre', model, w, 0.06, adaptve=True)              # a misspelt option is refused
    assert isinstance(make_law('lqr', model, w, 0.06, adaptive=False, pd_gains=None),
                      LqrLaw)  # off: fine
    # the registry holds every graph law, and the oracles once registered
    register_oracle_laws()
    assert set(GRAPH_LAWS) | set(ORACLE_LAWS) <= set(LAW_REGISTRY)
    with pytest.raises(ValueError, match='kp'):
        PdLaw(model, 0.06, kp=-1.0)


def test_state_dependent_weight_rises_with_the_error_and_is_capped():
    model = LinearModel(A21=-np.diag([300.0, 900.0]), G2=np.array([[10.0, 600.0], [-600.0, 5.0]]))
    law = AdaptiveSdreLaw(model, Weights(1e6, 0.0, 1.6e4), 1e9, n_fingers=1, lowpass_hz=0.0,
                          e_ref=1e-3, gain_max=4.0)
    p = REST[None, :2]
    z = np.zeros((1, 2))
    u0 = law.compute(p, z, p + [[0.0, 1e-4]], z).u
    assert law.gain == pytest.approx(1.01)
    law.compute(p, z, p + [[0.0, 1e-3]], z)
    assert law.gain == pytest.approx(2.0)
    u_big = law.compute(p, z, p + [[0.0, 5e-3]], z).u
    assert law.gain == 4.0
    fixed = SdreLaw(model, Weights(4e6, 0.0, 1.6e4), 1e9, n_fingers=1, lowpass_hz=0.0)
    np.testing.assert_allclose(u_big, fixed.compute(p, z, p + [[0.0, 5e-3]], z).u, rtol=1e-6)
    assert np.all(np.isfinite(u0))


def test_oracle_needs_the_plant_state():
    law = OracleSdreLaw(REST, Weights(1e6, 0.0, 1.6e4), 0.06, n_fingers=1)
    try:
        with pytest.raises(RuntimeError, match='observe'):
            law.compute(REST[None, :2], np.zeros((1, 2)), REST[None, :2], np.zeros((1, 2)))
        rest = SimpleNamespace(q=np.zeros((1, 10)), qd=np.zeros((1, 10)))
        law.observe(rest)
        out = law.compute(REST[None, :2], np.zeros((1, 2)), REST[None, :2] + [[0, 1e-3]],
                          np.zeros((1, 2)))
        assert out.ok.all() and np.all(np.isfinite(out.u)) and np.any(out.u != 0)
    finally:
        law.close()


SPRING = dict(A21=-np.diag([300.0, 900.0]), G2=np.array([[10.0, 600.0], [-600.0, 5.0]]))
W = Weights(1e6, 0.0, 1.6e4)


@pytest.mark.parametrize('ff_at', ['x', 'ref'])
def test_feedforward_on_the_reference_is_the_model_inversion(ff_at):
    """x = x_d: the feedback term vanishes and u = G₂⁻¹ (a_d − A₂₁ p_d − A₂₂ v_d), closed form."""
    law = SdreFeedforwardLaw(LinearModel(**SPRING), W, 1e9, n_fingers=1, lowpass_hz=0.0,
                             ff_at=ff_at)
    p, v, a = sine_reference(0.07)
    out = law.compute(p, v, p, v, ref_acc=a)
    u = np.linalg.solve(SPRING['G2'], a[0] - SPRING['A21'] @ (p[0] - REST[:2]))
    np.testing.assert_allclose(out.u[0], u, rtol=1e-12)
    assert out.ok.all() and not out.fallback.any()


def test_feedforward_at_x_makes_the_models_error_dynamics_the_closed_loop_matrix():
    """ff_at='x' on a state-dependent model: ẋ − ẋ_d = (A(x) + G(x)K(x)) (x − x_d) exactly."""
    model = StiffeningModel()
    law = SdreFeedforwardLaw(model, W, 1e9, n_fingers=3, lowpass_hz=0.0, method='reference',
                             ff_at='x')
    rng = np.random.default_rng(1)
    pos = REST[:2] + rng.normal(0, 3e-3, (3, 2))
    vel = rng.normal(0, 0.05, (3, 2))
    ref, ref_vel, ref_acc = (pos + rng.normal(0, 1e-3, (3, 2)), rng.normal(0, 0.05, (3, 2)),
                             rng.normal(0, 1, (3, 2)))
    out = law.compute(pos, vel, ref, ref_vel, ref_acc=ref_acc)
    x = np.concatenate([pos - REST[:2], vel], 1)
    xd = np.concatenate([ref - REST[:2], ref_vel], 1)
    A, G = model.AG(x)
    for i in range(3):
        K, _, _ = sdre_gains(A[i], G[i], W.Q, W.R)
        e_dot = A[i] @ x[i] + G[i] @ out.u[i] - np.concatenate([ref_vel[i], ref_acc[i]])
        np.testing.assert_allclose(e_dot, (A[i] + G[i] @ K) @ (x[i] - xd[i]), rtol=1e-7, atol=1e-9)


def test_feedforward_makes_a_sinusoid_an_exact_solution_where_the_paper_law_lags():
    """Linear SDC spring (A, G constant): started on the sine, the feedforward law tracks it up to
    the 0.2 ms zero-order hold; the paper's u = Kx + K_s x_d (same weights) lags by far more."""
    model = LinearModel(**SPRING)
    ff = SdreFeedforwardLaw(model, W, 1e9, n_fingers=1, lowpass_hz=0.0)
    paper = SdreLaw(model, W, 1e9, n_fingers=1, lowpass_hz=0.0)
    e_ff, e_paper = track_sine(ff, model), track_sine(paper, model)
    assert e_ff < 5e-6                     # of a 4 mm amplitude: the error of the hold alone
    assert e_paper > 100 * e_ff and e_paper > 1e-3


def test_feedforward_with_bad_reference_acceleration_still_gives_finite_torque():
    law = SdreFeedforwardLaw(LinearModel(**SPRING), W, 0.05, n_fingers=3, lowpass_hz=40.0)
    pos = REST[None, :2].repeat(3, 0)
    z = np.zeros((3, 2))
    acc = np.array([[np.nan, 1.0], [1e9, 0.0], [0.0, np.inf]])
    out = law.compute(pos, z, pos, z, ref_acc=acc)
    assert np.all(np.isfinite(out.u)) and np.all(np.abs(out.u) <= 0.05)
    np.testing.assert_array_equal(out.fallback, [True, False, True])     # no feedforward there
    np.testing.assert_array_equal(out.u[[0, 2]], 0.0)                    # on the reference, no a_d
    assert out.saturated[1].any() and out.ok.all()
    law.reset()
    none = law.compute(pos, z, pos + [[0, 1e-3]] * 3, z)                 # None: a_d = 0
    law.reset()
    zero = law.compute(pos, z, pos + [[0, 1e-3]] * 3, z, ref_acc=np.zeros((3, 2)))
    np.testing.assert_array_equal(none.u, zero.u)
    nan_state = law.compute(pos + [[np.nan, 0]] * 3, z, pos, z, ref_acc=np.ones((3, 2)))
    np.testing.assert_array_equal(nan_state.u_unsat, 0.0)               # no torque from a NaN state
    assert np.all(np.isfinite(nan_state.u)) and not nan_state.ok.any() and nan_state.fallback.all()
    with pytest.raises(ValueError, match='ref_acc'):
        law.compute(pos, z, pos, z, ref_acc=np.zeros((2, 2)))


def test_pd_feedforward_adds_the_reference_acceleration_and_make_law_knows_the_new_laws():
    G2 = SPRING['G2']
    pd = make_law('pd', LinearModel(G2=G2), W, 1e9, n_fingers=1, lowpass_hz=0.0, feedforward=True,
                  pd_gains=dict(kp=2000.0, kd=30.0))
    p, v, a = sine_reference(0.03)
    out = pd.compute(p, v, p + [[0, 1e-3]], v, ref_acc=a)
    np.testing.assert_allclose(G2 @ out.u[0], a[0] + [0, 2.0], rtol=1e-10)
    plain = make_law('pd', LinearModel(G2=G2), W, 1e9, n_fingers=1, lowpass_hz=0.0,
                     pd_gains=dict(kp=2000.0, kd=30.0))
    np.testing.assert_allclose(G2 @ plain.compute(p, v, p + [[0, 1e-3]], v, ref_acc=a).u[0],
                               [0, 2.0], atol=1e-12)  # without feedforward: a_d unused
    assert isinstance(make_law('sdre_ff', LinearModel(), W, 0.06), SdreFeedforwardLaw)
    assert make_law('sdre_ff', LinearModel(), W, 0.06, ff_at='ref').ff_at == 'ref'
    with pytest.raises(ValueError, match='ff_at'):
        make_law('sdre_ff', LinearModel(), W, 0.06, ff_at='later')
    with pytest.raises(ValueError,
                       match=r"feedforward=True .* is not an option of the 'sdre' law.*'pd'"):
        make_law('sdre', LinearModel(), W, 0.06, feedforward=True)
    register_oracle_laws()
    oracle = make_law('oracle_ff', LinearModel(), W, 0.06, n_fingers=1)
    try:
        assert isinstance(oracle, OracleFeedforwardLaw)
        with pytest.raises(RuntimeError, match='observe'):
            oracle.compute(REST[None, :2], np.zeros((1, 2)), REST[None, :2], np.zeros((1, 2)))
        oracle.observe(SimpleNamespace(q=np.zeros((1, 10)), qd=np.zeros((1, 10))))
        z = np.zeros((1, 2))
        still = oracle.compute(REST[None, :2], z, REST[None, :2], z, ref_acc=z).u
        push = oracle.compute(REST[None, :2], z, REST[None, :2], z,
                              ref_acc=np.array([[0.0, 1.0]])).u
        assert np.all(np.isfinite(push)) and np.any(push != still)
    finally:
        oracle.close()


@pytest.mark.parametrize('shapes', [((2, 3), (2, 1), (2, 2), (2, 2)),     # widths that add up to 8
                                    ((2, 2), (2, 2), (2, 1), (2, 3)),
                                    ((2,), (2, 2), (2, 2), (2, 2)),         # no silent broadcast
                                    ((1, 2), (1, 2), (1, 2), (1, 2))])      # too few fingers
def test_every_law_refuses_states_of_the_wrong_shape(shapes):
    laws = [SdreLaw(LinearModel(), Weights(1e4, 1.0, 1.0), 1.0, n_fingers=2),
            LqrLaw(LinearModel(), Weights(1e4, 1.0, 1.0), 1.0, n_fingers=2),
            SdreFeedforwardLaw(LinearModel(), Weights(1e4, 1.0, 1.0), 1.0, n_fingers=2),
            PdLaw(LinearModel(), 1.0, n_fingers=2)]
    args = [np.zeros(s) for s in shapes]
    for law in laws:
        with pytest.raises(ValueError, match=r'must each have shape \(2, 2\)'):
            law.compute(*args)
