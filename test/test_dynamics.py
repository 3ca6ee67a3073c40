"""Ground-truth task-space dynamics (soft_gripper_sdre.sim.dynamics) against the simulator."""
import numpy as np
import pytest

from soft_gripper_sdre.sim.dynamics import FingerDynamics, oracle_sdc
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.linear import linearize


@pytest.fixture(scope='module')
def fd():
    with FingerDynamics() as d:
        yield d


def _drive(sim, u, steps):
    for _ in range(steps):
        sim.step(np.asarray(u, float)[None])


def test_jacobian_and_input_matrix_match_the_simulators_finite_differences(fd):
    """J from PyBullet's analytic Jacobian equals linearize's finite-difference tip Jacobian,
    hence J M⁻¹ B too, at a bent pose (the hand's 15° mount)."""
    with GripperSim(SimConfig(scene='finger')) as sim:
        _drive(sim, [-0.04, 0.03], 300)
        truth = sim.truth()
        M, _, B, J = linearize(sim)
    d = fd.evaluate(truth.q[0], truth.qd[0])
    np.testing.assert_allclose(d.J, J[:2], atol=1e-8)
    np.testing.assert_allclose(d.G2, J[:2] @ np.linalg.solve(M, B), rtol=1e-6)
    # the sim's tip lags a substep
    np.testing.assert_allclose(d.tip_vel, truth.tip_vel[0, :2], rtol=0.05)


def test_predicted_tip_acceleration_matches_the_simulator_over_one_short_step(fd):
    """ẍ = J̇q̇ + J M⁻¹ (B u − K q − C q̇ − g − F sign q̇) against (J q̇)_{k+1} − (J q̇)_k over a 0.1 ms
    step of the simulator while every joint slips: within 2 % per axis (the rest is the friction
    motors' implicit, velocity-level solve)."""
    dt = 1e-4
    u = np.array([-0.05, 0.04])
    with GripperSim(SimConfig(scene='finger', control_period=dt, physics_substeps=1)) as sim:
        _drive(sim, u, 1000)
        before = sim.truth()
        assert np.all(np.abs(before.qd[0]) > 0.05)                    # every joint slips
        d0 = fd.evaluate(before.q[0], before.qd[0], friction=True)
        sim.step(u[None])
        after = sim.truth()
    d1 = fd.evaluate(after.q[0], after.qd[0])
    measured = (d1.tip_vel - d0.tip_vel) / dt
    predicted = d0.accel(u)
    np.testing.assert_allclose(predicted, measured, rtol=0.02)
    # without friction the prediction is off by more: friction is what the rest is
    frictionless = fd.evaluate(before.q[0], before.qd[0]).accel(u)
    assert np.abs(frictionless - measured).max() > np.abs(predicted - measured).max()


def test_gravity_follows_the_mounted_base(fd):
    """At a pose held still by a torque, the joint equation balances up to friction: the exact
    drift f_pos + G2 u is near zero (it would not be if gravity ignored the 15° mount)."""
    with GripperSim(SimConfig(scene='finger')) as sim:
        u = np.array([-0.03, 0.0])
        _drive(sim, u, 3000)
        truth = sim.truth()
    assert np.abs(truth.qd[0]).max() < 1e-3
    d = fd.evaluate(truth.q[0], truth.qd[0])
    wrong_gravity = FingerDynamics(mount_roll_deg=0.0)
    try:
        d_wrong = wrong_gravity.evaluate(truth.q[0], truth.qd[0])
    finally:
        wrong_gravity.close()
    resid = np.linalg.norm(d.f_pos + d.G2 @ u)
    assert resid < 0.2 * np.linalg.norm(d_wrong.f_pos + d_wrong.G2 @ u)


@pytest.mark.parametrize('reduced', [True, False])
def test_oracle_sdc_reproduces_the_true_drift_exactly(fd, reduced):
    rng = np.random.default_rng(3)
    q, qd = rng.normal(0, 0.05, 10), rng.normal(0, 1.0, 10)
    d = fd.evaluate(q, qd)
    rest = np.array([0.001, -0.002])
    A, G = oracle_sdc(d, rest, reduced=reduced)
    x = np.concatenate([d.tip - rest, d.tip_vel])
    u = np.array([0.01, -0.02])
    ref = d.reduced() if reduced else d
    np.testing.assert_allclose((A @ x + G @ u)[2:], ref.accel(u), rtol=1e-9)
    np.testing.assert_allclose((A @ x)[:2], d.tip_vel)
    A_qs = -ref.G2 @ np.linalg.inv(d.S)                # the quasi-static part of A21
    assert np.all(np.linalg.eigvals(A_qs).real < 0)    # is a stiffness (restoring)


def test_evaluate_refuses_bad_joint_states(fd):
    with pytest.raises(ValueError, match='10 entries'):
        fd.evaluate(np.zeros(9), np.zeros(10))
    with pytest.raises(ValueError, match='finite'):
        fd.evaluate(np.full(10, np.nan), np.zeros(10))
