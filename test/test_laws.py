"""The baseline laws (soft_gripper_sdre.laws) against closed forms."""
from types import SimpleNamespace

import numpy as np
import pytest

from soft_gripper_sdre.control import TrackingController, Weights
from soft_gripper_sdre.laws import (AdaptiveSdreLaw, LqrLaw, OracleSdreLaw, PdLaw, make_law)

REST = np.array([0.01, -0.02, 0.3])


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
        return np.broadcast_to(self._A, (n, 4, 4)).copy(), np.broadcast_to(self._G, (n, 4, 2)).copy()


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
    sdre = TrackingController(model, w, 1e9, n_fingers=2, method='reference', lowpass_hz=0.0)
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
    np.testing.assert_array_equal(out.u[1], [0.0, 0.0])           # no torque from a NaN reference
    np.testing.assert_allclose(out.u[0], [0.05, 0.0])             # first step: the filter starts there
    out = law.compute(pos, np.zeros((2, 2)), pos, np.zeros((2, 2)))
    a = np.exp(-2 * np.pi * 40.0 * 1e-3)
    np.testing.assert_allclose(out.u[0], [a * 0.05, 0.0])         # u_k = a u_{k−1} + (1 − a) · 0
    law.reset()
    assert np.all(law.compute(pos, np.zeros((2, 2)), pos, np.zeros((2, 2))).u == 0.0)


def test_make_law_names_and_options():
    model, w = LinearModel(), Weights(1e6, 0.0, 1.6e4)
    assert type(make_law('sdre', model, w, 0.06)) is TrackingController
    assert isinstance(make_law('sdre', model, w, 0.06, adaptive=True), AdaptiveSdreLaw)
    assert isinstance(make_law('lqr', model, w, 0.06), LqrLaw)
    assert isinstance(make_law('pd', model, w, 0.06), PdLaw)
    with pytest.raises(ValueError, match='unknown law .*known'):
        make_law('mpc', model, w, 0.06)
    with pytest.raises(ValueError, match='state-dependent weights'):
        make_law('pd', model, w, 0.06, adaptive=True)
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
    fixed = TrackingController(model, Weights(4e6, 0.0, 1.6e4), 1e9, n_fingers=1, lowpass_hz=0.0)
    np.testing.assert_allclose(u_big, fixed.compute(p, z, p + [[0.0, 5e-3]], z).u, rtol=1e-6)
    assert np.all(np.isfinite(u0))


def test_oracle_needs_the_plant_state():
    law = OracleSdreLaw(REST, Weights(1e6, 0.0, 1.6e4), 0.06, n_fingers=1)
    try:
        with pytest.raises(RuntimeError, match='observe'):
            law.compute(REST[None, :2], np.zeros((1, 2)), REST[None, :2], np.zeros((1, 2)))
        rest = SimpleNamespace(q=np.zeros((1, 10)), qd=np.zeros((1, 10)))
        law.observe(rest)
        out = law.compute(REST[None, :2], np.zeros((1, 2)), REST[None, :2] + [[0, 1e-3]], np.zeros((1, 2)))
        assert out.ok.all() and np.all(np.isfinite(out.u)) and np.any(out.u != 0)
    finally:
        law.close()
