"""The constant-velocity KF against closed forms."""
import numpy as np
import pytest
from scipy.linalg import expm

from soft_gripper_sdre.control.kf import ConstantVelocityKF, cv_matrices

A = np.block([[np.zeros((2, 2)), np.eye(2)], [np.zeros((2, 2)), np.zeros((2, 2))]])


@pytest.mark.parametrize('model, D', [
    ('independent', np.vstack([np.zeros((2, 2)), np.eye(2)])),
    ('paper', np.array([[0.0], [0.0], [1.0], [1.0]]))])
def test_F_and_process_noise_match_van_loan(model, D):
    dt, q = 1e-3, 3.0
    F, Q = cv_matrices(dt, q, model)
    np.testing.assert_allclose(F, expm(A * dt))
    # van Loan: expm([[−A, D q Dᵀ], [0, Aᵀ]] Δt) = [[·, F⁻¹ Q], [0, Fᵀ]]
    M = np.block([[-A, D @ D.T * q], [np.zeros((4, 4)), A.T]]) * dt
    E = expm(M)
    Q_vl = E[4:, 4:].T @ E[:4, 4:]
    np.testing.assert_allclose(Q, Q_vl, rtol=1e-9, atol=1e-18)


def test_covariance_converges_to_the_dare_solution():
    kf = ConstantVelocityKF(1e-3, 10.0, 5e-5, n=2)
    rng = np.random.default_rng(0)
    for _ in range(5000):
        kf.step(rng.normal(size=(2, 2)) * 5e-5)
    S_inf, K_inf = kf.steady_state()
    # the prior after one more predict equals the DARE solution
    P_prior = kf.F @ kf.P[0] @ kf.F.T + kf.Q
    np.testing.assert_allclose(P_prior, S_inf, rtol=1e-6)


def test_noiseless_constant_velocity_track_is_recovered_exactly():
    dt = 1e-3
    kf = ConstantVelocityKF(dt, 1.0, 1e-6, n=3)
    p0 = np.array([[0.01, -0.02], [0.0, 0.0], [0.1, 0.2]])
    v = np.array([[0.05, -0.01], [0.0, 0.02], [-0.03, 0.0]])
    kf.reset(p0)
    for k in range(1, 3000):
        x = kf.step(p0 + v * k * dt)
    np.testing.assert_allclose(x[:, 2:], v, atol=1e-8)
    np.testing.assert_allclose(x[:, :2], p0 + v * 2999 * dt, atol=1e-10)


def test_velocity_noise_is_far_below_differentiated_measurement_noise():
    dt, sigma = 1e-3, 5e-5
    kf = ConstantVelocityKF(dt, 1e-2, sigma, n=1)   # q matched to the track's accelerations
    rng = np.random.default_rng(1)
    t = np.arange(4000) * dt
    truth = np.stack([0.01 * np.sin(2 * t), 0.01 * np.cos(3 * t)], axis=1)
    z = truth + rng.normal(size=truth.shape) * sigma
    kf.reset(z[:1])
    est = np.array([kf.step(z[k:k + 1])[0] for k in range(1, len(t))])
    vel_true = np.stack([0.02 * np.cos(2 * t), -0.03 * np.sin(3 * t)], axis=1)[1:]
    err_kf = np.sqrt(np.mean((est[1000:, 2:] - vel_true[1000:]) ** 2))
    err_fd = np.sqrt(np.mean((np.diff(z, axis=0)[1000:] / dt - vel_true[1000:]) ** 2))
    assert err_kf < err_fd / 15 and err_kf < 0.15 * 0.03


def test_invalid_rows_only_predict():
    kf = ConstantVelocityKF(1e-3, 1.0, 1e-4, n=2)
    kf.reset(np.zeros((2, 2)))
    x = kf.step(np.array([[1e-3, 0.0], [np.nan, np.nan]]), valid=np.array([True, True]))
    assert np.all(np.isfinite(x)) and x[1, 0] == 0.0 and x[0, 0] > 0
    x_before, P_before = kf.x.copy(), kf.P.copy()
    kf.step(np.array([[1e-3, 0.0], [1e-3, 0.0]]), valid=np.array([False, True]))
    F, Q = kf.F, kf.Q
    np.testing.assert_allclose(kf.x[0], F @ x_before[0], rtol=1e-14, atol=1e-18)  # row 0: predicted
    np.testing.assert_allclose(kf.P[0], F @ P_before[0] @ F.T + Q, rtol=1e-14, atol=1e-18)
    assert kf.x[1, 0] > F[0] @ x_before[1]                                        # row 1: updated
    x_before = kf.x.copy()
    kf.step(np.zeros((2, 2)), valid=False)                   # no row valid: a prediction for both
    np.testing.assert_allclose(kf.x, x_before @ F.T, rtol=1e-14, atol=1e-18)


@pytest.mark.parametrize('kwargs, match', [
    (dict(dt=0.0), 'dt'), (dict(accel_psd=-1.0), 'accel_psd'), (dict(meas_std=0.0), 'meas_std'),
    (dict(process_noise='coloured'), 'process_noise')])
def test_bad_arguments(kwargs, match):
    args = dict(dt=1e-3, accel_psd=1.0, meas_std=1e-4)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        ConstantVelocityKF(**args)
    with pytest.raises(ValueError, match='z must'):
        ConstantVelocityKF(1e-3, 1.0, 1e-4, n=2).step(np.zeros((3, 2)))


@pytest.mark.parametrize('model', ['independent', 'paper'])
def test_variable_steps_match_filterpy_with_the_same_dt_sequence(model):
    """Jittered steps (100–400 Hz, ±20 %) and a bridged dropout: the compiled per-step F and Σ_v
    give filterpy's KalmanFilter (Joseph-form update) fed cv_matrices of each step's Δt."""
    from filterpy.kalman import KalmanFilter
    rng = np.random.default_rng(11)
    q, sigma, n = 2.0, 5e-5, 3
    dts = np.concatenate([rng.uniform(0.8, 1.2, 150) / 120, rng.uniform(0.8, 1.2, 150) / 400,
                          [0.031]])
    rng.shuffle(dts)
    t = np.cumsum(dts)
    truth = rng.normal(size=(n, 2)) * 1e-3 + rng.normal(size=(n, 2)) * 0.02 * t[:, None, None]
    z = truth + rng.normal(size=truth.shape) * sigma
    kf = ConstantVelocityKF(1 / 120, q, sigma, n=n, process_noise=model)
    kf.reset(z[0])
    refs = []
    for i in range(n):
        ref = KalmanFilter(dim_x=4, dim_z=2)
        ref.x, ref.P = kf.x[i].copy(), kf.P[i].copy()
        ref.H, ref.R = kf.H, kf.R
        refs.append(ref)
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        got = kf.step(z[k], dt=dt)
        F, Q = cv_matrices(dt, q, model)
        for i, ref in enumerate(refs):
            ref.predict(F=F, Q=Q)
            ref.update(z[k, i])
            np.testing.assert_allclose(got[i], ref.x, rtol=1e-7, atol=1e-9)
            np.testing.assert_allclose(kf.P[i], ref.P, rtol=1e-7, atol=1e-16)
    assert np.abs(got[:, :2] - truth[-1]).max() < 5 * sigma


def test_a_step_of_the_filters_own_dt_is_the_fixed_step_bit_for_bit():
    rng = np.random.default_rng(2)
    fixed, given = (ConstantVelocityKF(1e-3, 1.0, 5e-5, n=4) for _ in range(2))
    for k in range(50):
        z = rng.normal(size=(4, 2)) * 1e-3
        np.testing.assert_array_equal(fixed.step(z), given.step(z, dt=1e-3))
    np.testing.assert_array_equal(fixed.P, given.P)


def test_compiled_matrices_agree_with_cv_matrices():
    from soft_gripper_sdre.control.kernels import kf_step_dt
    for model, coupling in (('independent', 0.0), ('paper', 1.0)):
        for dt in (1e-4, 8.3e-3, 0.05):
            F, Q = np.empty((4, 4)), np.empty((4, 4))
            x, P = np.zeros((1, 4)), np.zeros((1, 4, 4))
            kf_step_dt(x, P, np.zeros((1, 2)), np.zeros(1, dtype=np.bool_), dt, 3.0, coupling, F, Q,
                       np.eye(2))
            F_ref, Q_ref = cv_matrices(dt, 3.0, model)
            np.testing.assert_array_equal(F, F_ref)
            np.testing.assert_allclose(Q, Q_ref, rtol=1e-15, atol=0)
            np.testing.assert_allclose(P[0], Q_ref, rtol=1e-15, atol=0)   # predicted from P = 0


@pytest.mark.parametrize('dt', [0.0, -1e-3, float('nan'), float('inf')])
def test_a_step_over_a_bad_dt_is_refused_and_leaves_the_filter(dt):
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=2)
    kf.reset(np.ones((2, 2)))
    before = kf.x.copy(), kf.P.copy()
    with pytest.raises(ValueError, match='dt must be finite and > 0'):
        kf.step(np.zeros((2, 2)), dt=dt)
    np.testing.assert_array_equal(kf.x, before[0])
    np.testing.assert_array_equal(kf.P, before[1])
