"""The SDRE law against closed forms; the fast path against the reference; fallbacks."""
import numpy as np
import pytest

from soft_gripper_sdre.control.riccati import (
    Check,
    care,
    is_detectable,
    is_stabilizable,
    sdre_gains,
)
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import paper_weights_si

A_DI = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]], dtype=float)
G_DI = np.vstack([np.zeros((2, 2)), np.eye(2)])


def test_scalar_lqr_gain_is_sqrt_q_over_r():
    q, r = 7.0, 0.3
    P = care(np.zeros((1, 1)), np.ones((1, 1)), np.array([[q]]), np.array([[r]]))
    K = -P / r
    assert K[0, 0] == pytest.approx(-np.sqrt(q / r))


def test_double_integrator_closed_form():
    q1, q2, r = 4.0, 1.0, 0.25
    Q, R = np.diag([q1, q1, q2, q2]), np.diag([r, r])
    K, Ks, P = sdre_gains(A_DI, G_DI, Q, R)
    # per axis: p12 = √(q1 r), p22 = √(r (q2 + 2 p12)), p11 = p12 p22 / r
    p12 = np.sqrt(q1 * r)
    p22 = np.sqrt(r * (q2 + 2 * p12))
    p11 = p12 * p22 / r
    np.testing.assert_allclose(P[0, 0], p11)
    np.testing.assert_allclose(P[0, 2], p12)
    np.testing.assert_allclose(P[2, 2], p22)
    np.testing.assert_allclose(K[0], [-p12 / r, 0, -p22 / r, 0])


def test_constant_reference_reached_on_a_double_integrator():
    """For ẍ = u the law's steady state x = −A_cl⁻¹ G K_s x_d equals x_d in position."""
    Q, R = np.diag([100.0, 100.0, 1.0, 1.0]), np.diag([0.1, 0.1])
    K, Ks, _ = sdre_gains(A_DI, G_DI, Q, R)
    A_cl = A_DI + G_DI @ K
    x_d = np.array([0.3, -0.2, 0.0, 0.0])
    x_ss = -np.linalg.solve(A_cl, G_DI @ Ks @ x_d)
    np.testing.assert_allclose(x_ss[:2], x_d[:2], atol=1e-9)


def _slowly_varying_plant(k, n=4):
    rng = np.random.default_rng(0)
    base21 = rng.normal(size=(n, 2, 4)) * 5
    A = np.zeros((n, 4, 4))
    A[:, 0, 2] = A[:, 1, 3] = 1.0
    A[:, 2:, :] = base21 + 0.5 * np.sin(0.01 * k)
    G = np.zeros((n, 4, 2))
    G[:, 2:, :] = np.array([[1.0, 30.0], [-30.0, 1.0]]) * (1 + 0.1 * np.cos(0.01 * k))
    return A, G


def test_fast_path_matches_reference_on_a_sequence():
    Q, R = np.diag([4e6, 4e6, 4e3, 4e3]), np.diag([1.6e4, 1.6e4])
    fast = SdreController(Q, R, 1.0, method='fast')
    ref = SdreController(Q, R, 1.0, method='reference')
    rng = np.random.default_rng(1)
    for k in range(200):
        A, G = _slowly_varying_plant(k)
        x, xd = rng.normal(size=(4, 4)) * 1e-3, rng.normal(size=(4, 4)) * 1e-3
        a, b = fast.step(A, G, x, xd), ref.step(A, G, x, xd)
        assert a.ok.all() and b.ok.all()
        # the fast path's stated tolerance (test_sdre_fast.py U_TOL): 1e-4 of the step's largest
        # torque
        np.testing.assert_allclose(a.u, b.u, rtol=0, atol=1e-4 * np.abs(b.u).max())
    assert fast.exact_solves <= 8            # cold start, then Newton–Kleinman
    assert fast.fallbacks == 0


def test_singular_input_matrix_falls_back_to_last_valid_gains():
    Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.diag([1.0, 1.0])
    for method in ('fast', 'reference'):
        c = SdreController(Q, R, 0.5, n=1, method=method)
        good = c.step(A_DI[None], G_DI[None], np.ones((1, 4)) * 0.1, np.zeros((1, 4)))
        G_bad = np.zeros((1, 4, 2))
        G_bad[0, 2:, :] = [[1.0, 1.0], [1.0, 1.0]]  # rank 1: Y and X not independently actuated
        out = c.step(A_DI[None], G_bad, np.ones((1, 4)) * 0.1, np.zeros((1, 4)))
        assert out.fallback[0] and not out.ok[0] and out.failed_checks[0] & Check.STABILIZABLE
        np.testing.assert_allclose(out.K, good.K)
        assert np.all(np.isfinite(out.u)) and c.fallbacks == 1


def test_nonfinite_model_output_gives_finite_bounded_torque():
    c = SdreController(np.eye(4), np.eye(2), 0.2, n=2)
    A = np.stack([A_DI, A_DI])
    A[1, 2, 0] = np.nan
    out = c.step(A, np.stack([G_DI, G_DI]), np.ones((2, 4)), np.zeros((2, 4)))
    assert np.all(np.isfinite(out.u)) and np.all(np.abs(out.u) <= 0.2)
    assert out.ok[0] and out.failed_checks[1] & Check.NONFINITE
    np.testing.assert_array_equal(out.u[1], 0.0)     # no valid gains yet: zero torque


def test_saturation():
    c = SdreController(np.eye(4) * 1e4, np.eye(2), [0.1, 0.2], n=1)
    out = c.step(A_DI[None], G_DI[None], np.array([[1.0, -1.0, 0, 0]]), np.zeros((1, 4)))
    np.testing.assert_allclose(np.abs(out.u), [[0.1, 0.2]])
    assert out.saturated.all()


def test_paper_weights_in_si():
    Q, R = paper_weights_si()
    np.testing.assert_allclose(np.diag(Q), 800.0)
    np.testing.assert_allclose(np.diag(R), 16000.0)


@pytest.mark.parametrize('Q, R, u_max, match', [
    (-np.eye(4), np.eye(2), 1.0, 'Q must be symmetric positive semi-definite'),
    (np.eye(3), np.eye(2), 1.0, 'Q must be'),
    (np.eye(4), np.zeros((2, 2)), 1.0, 'R must be symmetric positive definite'),
    (np.eye(4), np.eye(2), 0.0, 'u_max'),
])
def test_bad_weights(Q, R, u_max, match):
    with pytest.raises(ValueError, match=match):
        SdreController(Q, R, u_max)


def test_sdre_law_roll_off_is_a_first_order_filter():
    """With the roll-off, a constant law output is approached as 1 − aᵏ (a = e^{−2π f Δt})."""
    from soft_gripper_sdre.control.laws import SdreLaw
    from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.learning.model import SDCModel
    model = SDCModel()
    rest = np.repeat(model.rest_tip[None, :2], 4, 0)
    ref = rest + [0.0, 0.002]
    plain = SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, lowpass_hz=0.0)
    rolled = SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, lowpass_hz=40.0, dt=1e-3)
    zero = np.zeros((4, 2))
    u_star = plain.compute(rest, zero, ref, zero).u
    a = np.exp(-2 * np.pi * 40.0 * 1e-3)
    first = rolled.compute(rest, zero, ref, zero).u
    np.testing.assert_allclose(first, u_star)                    # starts at the law's output
    rolled.reset()
    np.testing.assert_array_equal(rolled.compute(rest, zero, rest, zero).u, 0.0)   # at rest: 1 − aᵏ
    for k in range(1, 6):
        u = rolled.compute(rest, zero, ref, zero).u
        np.testing.assert_allclose(u, (1 - a**k) * u_star, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match='lowpass_hz'):
        SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, lowpass_hz=-1.0)


def test_pbh_tests_find_an_unstable_mode_that_the_input_or_the_output_misses():
    """A double integrator per axis: stabilisable through both inputs, not when one axis is
    unactuated; detectable from both positions, not from the velocities alone (the positions drift
    unseen)."""
    assert is_stabilizable(A_DI, G_DI)
    assert not is_stabilizable(A_DI, G_DI[:, :1])
    assert is_detectable(A_DI, np.hstack([np.eye(2), np.zeros((2, 2))]))
    assert not is_detectable(A_DI, np.hstack([np.zeros((2, 2)), np.eye(2)]))
    stable = -np.eye(4)
    assert is_stabilizable(stable, np.zeros((4, 2))) and is_detectable(stable, np.zeros((1, 4)))


def test_the_roll_off_corner_is_capped_at_a_tenth_of_the_sampling_rate():
    """40 Hz up to a 2.5 ms period (the 1 ms filter bit for bit), then 0.1 / Δt; off stays off."""
    from soft_gripper_sdre.control.tracking import RollOff, roll_off_corner_hz
    assert RollOff(40.0, 1e-3).alpha == np.exp(-2 * np.pi * 40.0 * 1e-3)
    assert roll_off_corner_hz(40.0, 2e-3) == 40.0
    assert roll_off_corner_hz(40.0, 5e-3) == pytest.approx(20.0)
    assert RollOff(40.0, 1e-2).hz == pytest.approx(10.0)
    assert roll_off_corner_hz(7.5, 1e-2) == 7.5                   # a lower corner is kept
    assert RollOff(0.0, 1e-2).alpha == 0.0
    for dt in (0.0, -1e-3, float('nan')):
        with pytest.raises(ValueError, match='control period'):
            RollOff(40.0, dt)
