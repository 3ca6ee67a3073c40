"""The fast SDRE path (the compiled kernels under the supervisor) against the reference path
(scipy) on the shipped model, and its checks.

Tolerance: the kernel stops Newton–Kleinman once a bound on the next iterate's Riccati residual is
below half the accepted 1e-6 (relative to ‖Q‖_F) and forms the residual directly for its checks;
its gains, P and the unsaturated torques agree with scipy's to within ``U_TOL`` = 1e-4 of the
largest value of the sequence, and are held to ``REGRESSION_TOL`` = 2e-5 so that a loss of
accuracy shows long before the tolerance (docs/design/compiled_kernel.md, "Accuracy"). 1e-4 of the
0.0625 N·m limit is 6 µN·m, far below the torque jitter the 0.05 mm measurement noise causes. Every
check passes on both paths, and the fast path solves exactly only on the cold start.
"""
import time

import numpy as np
import pytest

from soft_gripper_sdre.control.batched_linalg import (
    batched_solve,
    portable_batched_solve,
    well_conditioned_2x2,
)
from soft_gripper_sdre.control.kernels.linalg import well_conditioned
from soft_gripper_sdre.control.laws import SdreLaw
from soft_gripper_sdre.control.riccati import Check, care, full_sdc_matrices
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import SDCModel

U_TOL = 1e-4
#: an accuracy regression trips it long before the stated tolerance would
REGRESSION_TOL = 2e-5
N = 4


@pytest.fixture(scope='module')
def model():
    return SDCModel()


def trajectory_states(model, steps, noise, seed):
    """Tip states of a smooth 4-finger motion (a few mm, tens of mm/s) plus white measurement-like
    noise on positions and velocities, as the KF hands them to the controller (base frames, SI)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * 1e-3
    phase = rng.uniform(0, 2 * np.pi, (N, 2))
    amp = rng.uniform(1e-3, 6e-3, (N, 2))
    w = 2 * np.pi * rng.uniform(0.3, 1.5, (N, 2))
    pos = model.rest_tip[:2] + amp * np.sin(w * t[:, None, None] + phase)
    vel = amp * w * np.cos(w * t[:, None, None] + phase)
    pos = pos + noise[0] * rng.standard_normal(pos.shape)
    vel = vel + noise[1] * rng.standard_normal(vel.shape)
    ref = model.rest_tip[:2] + amp * np.sin(w * (t[:, None, None] + 0.05) + phase)
    return pos, vel, ref, np.zeros_like(vel)


def run_both(model, pos, vel, ref, ref_vel):
    ctrl = {m: SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, method=m, lowpass_hz=0.0)
            for m in ('fast', 'reference')}
    out = {m: [c.compute(pos[k], vel[k], ref[k], ref_vel[k]) for k in range(len(pos))]
           for m, c in ctrl.items()}
    return ctrl, out


@pytest.mark.parametrize('noise', [(0.0, 0.0), (5e-5, 5e-3)], ids=['clean', 'noisy'])
def test_fast_torques_equal_the_reference_along_a_trajectory(model, noise):
    pos, vel, ref, ref_vel = trajectory_states(model, 150, noise, seed=3)
    ctrl, out = run_both(model, pos, vel, ref, ref_vel)
    uf = np.array([o.u_unsat for o in out['fast']])
    ur = np.array([o.u_unsat for o in out['reference']])
    assert all(o.ok.all() for o in out['fast']) and all(o.ok.all() for o in out['reference'])
    scale = np.abs(ur).max()
    assert scale > 1e-3                                   # the law does something
    np.testing.assert_allclose(uf, ur, rtol=0, atol=U_TOL * scale)
    assert np.abs(uf - ur).max() <= REGRESSION_TOL * scale
    for o_f, o_r in zip(out['fast'], out['reference']):
        np.testing.assert_allclose(o_f.K, o_r.K, rtol=0, atol=U_TOL * np.abs(o_r.K).max())
        np.testing.assert_allclose(o_f.Ks, o_r.Ks, rtol=0, atol=U_TOL * np.abs(o_r.Ks).max())
        assert np.all(o_f.residual < 1e-6)
    # the fast path really ran: exact solves only for the cold start, Newton–Kleinman after it
    assert ctrl['fast'].sdre.exact_solves == N and ctrl['fast'].sdre.fallbacks == 0
    assert all(o.nk_iterations.min() >= 1 for o in out['fast'][1:])


def test_fast_torques_equal_the_reference_at_random_states(model):
    """Random states over the workspace; each is reached from a state 0.1 mm / 5 mm/s away."""
    rng = np.random.default_rng(11)
    fast = SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, lowpass_hz=0.0)
    ref = SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, method='reference', lowpass_hz=0.0)
    zero = np.zeros((N, 2))
    for _ in range(25):
        pos = model.rest_tip[:2] + rng.uniform(-8e-3, 8e-3, (N, 2))
        vel = rng.uniform(-0.05, 0.05, (N, 2))
        goal = model.rest_tip[:2] + rng.uniform(-8e-3, 8e-3, (N, 2))
        fast.compute(pos, vel, goal, zero)                 # warm start near the state
        pos2, vel2 = (pos + 1e-4 * rng.standard_normal((N, 2)),
                      vel + 5e-3 * rng.standard_normal((N, 2)))
        a, b = fast.compute(pos2, vel2, goal, zero), ref.compute(pos2, vel2, goal, zero)
        assert a.ok.all() and b.ok.all() and a.nk_iterations.min() >= 1
        np.testing.assert_allclose(a.u_unsat, b.u_unsat, rtol=0,
                                   atol=REGRESSION_TOL * np.abs(b.u_unsat).max())
        np.testing.assert_allclose(a.P, b.P, rtol=0, atol=U_TOL * np.abs(b.P).max())


def test_closed_form_condition_test_equals_the_svd():
    """The 2×2 condition test without an SVD, batched (the reference path) and compiled (the
    kernels)."""
    rng = np.random.default_rng(5)
    M = rng.normal(size=(2000, 2, 2))
    M[:500, 1] = M[:500, 0] * (1 + 10.0 ** rng.uniform(-12, -4, (500, 1)))   # near-singular
    M[500:510] = 0.0
    kappa = np.linalg.cond(M)
    for c_max in (1e3, 1e8):
        fast, det = well_conditioned_2x2(M, c_max)
        np.testing.assert_allclose(det, np.linalg.det(M), rtol=1e-9, atol=1e-14)
        clear = np.abs(np.log(kappa / c_max)) > 1e-6            # away from the threshold's rounding
        np.testing.assert_array_equal(fast[clear], (kappa < c_max)[clear])
        compiled = np.array([well_conditioned(m, c_max) for m in M])
        np.testing.assert_array_equal(compiled[clear], (kappa < c_max)[clear])
    bad = np.full((1, 2, 2), np.nan)
    assert not well_conditioned_2x2(bad, 1e8)[0][0] and not well_conditioned(bad[0], 1e8)


def test_batched_solve_equals_the_public_solve_and_flags_failures_with_nan():
    """The batched solve in use (numpy's gufunc) and the portable fallback agree: the same
    solutions, and NaN exactly for the singular and the non-finite matrices."""
    rng = np.random.default_rng(7)
    L = rng.normal(size=(6, 2, 2)) + 5 * np.eye(2)
    L[1] = 0.0                                                   # singular
    L[2, 0] = np.nan                                             # not finite
    b = rng.normal(size=(6, 2))
    with np.errstate(all='ignore'):
        for solve in (batched_solve, portable_batched_solve):
            x = solve(L, b)
            assert x.shape == b.shape
            assert list(np.isfinite(x).all(axis=1)) == [True, False, False, True, True, True]
            good = [0, 3, 4, 5]
            np.testing.assert_allclose(x[good],
                                       np.linalg.solve(L[good], b[good][..., None])[..., 0],
                                       rtol=1e-12)


def sdc_plant(model, rng):
    x = np.concatenate([rng.uniform(-3e-3, 3e-3, (N, 2)), rng.uniform(-0.02, 0.02, (N, 2))], axis=1)
    a, g = model.sdc_blocks(x)
    return x, a.copy(), g.copy()


def warm(ctrl, a, g, x):
    out = ctrl.step_sdc(a, g, x, np.zeros((N, 4)))
    assert out.ok.all()
    return out


def test_fast_path_rejects_the_anti_stabilising_solution(model):
    """Warm-started at the ARE's anti-stabilising solution (a fixed point of Newton's iteration),
    the kernel's P ≻ 0 / Lyapunov test rejects it, and its solve from scratch gives the right
    gains without an exact solve."""
    rng = np.random.default_rng(2)
    W = Weights(**DEFAULT_WEIGHTS)
    ctrl = SdreController(W.Q, W.R, 0.0625, n=N)
    x, a, g = sdc_plant(model, rng)
    warm(ctrl, a, g, x)
    A, G = full_sdc_matrices(a, g)
    anti = np.stack([-care(-A[i], G[i], W.Q, W.R) for i in range(N)])  # A − S P⁻ anti-Hurwitz
    assert np.all(np.linalg.eigvals(A - G @ np.linalg.solve(W.R, G.transpose(0, 2, 1))
                                    @ anti).real > 0)
    ctrl.warm_start(anti)
    before = ctrl.exact_solves
    out = ctrl.step_sdc(a, g, x, np.zeros((N, 4)))
    ref = SdreController(W.Q, W.R, 0.0625, n=N,
                         method='reference').step_sdc(a, g, x, np.zeros((N, 4)))
    assert out.ok.all() and ctrl.exact_solves == before and np.all(out.nk_iterations >= 1)
    assert not out.failed_checks.any()
    np.testing.assert_allclose(out.K, ref.K, rtol=1e-9)
    assert ctrl.step_sdc(a, g, x, np.zeros((N, 4))).nk_iterations.min() >= 1    # back on the kernel


def test_fast_path_checks_still_trigger(model):
    """Singular G2 (not stabilisable), NaN from the model, NaN state: flagged, fallback, finite
    u."""
    rng = np.random.default_rng(4)
    W = Weights(**DEFAULT_WEIGHTS)
    ctrl = SdreController(W.Q, W.R, 0.0625, n=N)
    x, a, g = sdc_plant(model, rng)
    good = warm(ctrl, a, g, x)
    warm(ctrl, a, g, x)                          # now on the fast path
    assert ctrl.exact_solves == N
    g_bad, a_bad, x_bad = g.copy(), a.copy(), x.copy()
    g_bad[0, 1] = g_bad[0, 0] * 3.0              # rank 1: the two torques act along one direction
    a_bad[1, 0, 2] = np.nan
    x_bad[2, 3] = np.inf
    out = ctrl.step_sdc(a_bad, g_bad, x_bad, np.zeros((N, 4)))
    assert out.failed_checks[0] & Check.STABILIZABLE and out.failed_checks[1] & Check.NONFINITE
    assert out.failed_checks[2] & Check.NONFINITE
    assert list(out.fallback) == [True, True, True, False] and out.ok[3]
    np.testing.assert_allclose(out.K[:2], good.K[:2])       # last valid gains
    assert np.all(np.isfinite(out.u)) and np.all(out.u[2] == 0.0)
    # after a rejected step that finger starts cold again, then returns to the fast path
    out = ctrl.step_sdc(a, g, x, np.zeros((N, 4)))
    assert out.ok.all() and list(out.nk_iterations == 0) == [True, True, True, False]
    out = ctrl.step_sdc(a, g, x, np.zeros((N, 4)))
    assert out.ok.all() and out.nk_iterations.min() >= 1


def test_stop_rule_trace_bound_holds_for_a_newton_kleinman_step(model):
    """The stop rule's bound: for a Newton–Kleinman step from any P_k near the solution,
    ‖Res(P_k+1)‖_F ≤ ⟨Δ_low, W Δ_low⟩ ≤ ‖W‖_F ‖Δ_low‖_F² (a coarser bound), with
    Δ = P_k+1 − P_k, W = G2 R⁻¹ G2ᵀ; computed here on full matrices with scipy's Lyapunov solver."""
    from scipy.linalg import solve_continuous_lyapunov
    rng = np.random.default_rng(7)
    W_ = Weights(**DEFAULT_WEIGHTS)
    Q, R = W_.Q, W_.R
    x, a, g = sdc_plant(model, rng)
    A, G = full_sdc_matrices(a, g)
    S = G @ np.linalg.inv(R) @ G.transpose(0, 2, 1)
    for i in range(N):
        P_star = care(A[i], G[i], Q, R)
        for scale in (1e-1, 1e-2, 1e-3):
            E = rng.standard_normal((4, 4))
            P_k = P_star * (1.0 + scale * (E + E.T) / 2)  # a nearby symmetric warm start
            A_k = A[i] - S[i] @ P_k
            P_next = solve_continuous_lyapunov(A_k.T, -(Q + P_k @ S[i] @ P_k))
            res = np.linalg.norm(P_next @ A[i] + A[i].T @ P_next + Q - P_next @ S[i] @ P_next)
            D = (P_next - P_k)[2:, :]
            Wi = S[i][2:, 2:]
            trace = np.vdot(D, Wi @ D)
            assert res <= trace * (1 + 1e-6) + 1e-9 * np.linalg.norm(Q)
            assert trace <= np.linalg.norm(Wi) * np.vdot(D, D) * (1 + 1e-12)


def test_a_steps_arrays_are_its_own(model):
    """A step's gains and torques do not change under later steps (also ones that fall back and
    update the gains of the fingers that passed), and writing into them does not reach the
    controller."""
    rng = np.random.default_rng(5)
    W = Weights(**DEFAULT_WEIGHTS)
    ctrl = SdreController(W.Q, W.R, 0.0625, n=N)
    x, a, g = sdc_plant(model, rng)
    warm(ctrl, a, g, x)
    first = warm(ctrl, a, g, x)                  # a fast-path step
    assert first.nk_iterations.min() >= 1
    K, Ks, u = first.K.copy(), first.Ks.copy(), first.u.copy()
    a2 = a * (1.0 + 1e-2 * rng.standard_normal(a.shape))
    a2[1, 0, 2] = np.nan                         # finger 1 falls back, the others get new gains
    out = ctrl.step_sdc(a2, g, x, np.zeros((N, 4)))
    assert out.fallback[1] and out.ok[[0, 2, 3]].all()
    assert not np.allclose(out.K[0], K[0])
    np.testing.assert_array_equal(first.K, K)
    np.testing.assert_array_equal(first.Ks, Ks)
    np.testing.assert_array_equal(first.u, u)
    np.testing.assert_array_equal(out.K[1], K[1])                       # the last valid gains
    out.K[:] = 0.0
    out.Ks[:] = 0.0
    again = ctrl.step_sdc(a2, g, x, np.zeros((N, 4)))
    np.testing.assert_array_equal(again.K[1], K[1])


def test_fast_path_without_the_fused_network_and_weights_it_cannot_take(model):
    """A model with only ``sdc_blocks`` runs the kernel on its blocks; a Q whose position block is
    singular (no detectability through the SDC form) takes the reference path, bit for bit."""

    class BlocksOnly:
        rest_tip = model.rest_tip

        def sdc_blocks(self, x):
            return model.sdc_blocks(x)

    pos, vel, ref, ref_vel = trajectory_states(model, 40, (5e-5, 5e-3), seed=4)
    w = Weights(**DEFAULT_WEIGHTS)
    blocks, fused, reference = (SdreLaw(m, w, 0.0625, method=meth, lowpass_hz=0.0)
                                for m, meth in ((BlocksOnly(), 'fast'), (model, 'fast'),
                                                (model, 'reference')))
    assert blocks.network is None and fused.network is not None and blocks.sdre.fast
    for k in range(len(pos)):
        b, f, r = (law.compute(pos[k], vel[k], ref[k], ref_vel[k])
                   for law in (blocks, fused, reference))
        np.testing.assert_allclose(b.u_unsat, f.u_unsat, rtol=0,
                                   atol=1e-9 * np.abs(f.u_unsat).max())
        np.testing.assert_allclose(b.u_unsat, r.u_unsat, rtol=0,
                                   atol=U_TOL * np.abs(r.u_unsat).max())
    assert blocks.sdre.exact_solves == N
    velocity_only = Weights(0.0, 1.0, 1.0)
    fast, ref_law = (SdreLaw(model, velocity_only, 0.0625, method=m, lowpass_hz=0.0)
                     for m in ('fast', 'reference'))
    assert not fast.sdre.fast and fast.network is None
    for k in range(5):
        a, b = (law.compute(pos[k], vel[k], ref[k], ref_vel[k]) for law in (fast, ref_law))
        np.testing.assert_array_equal(a.u, b.u)
        np.testing.assert_array_equal(a.failed_checks, b.failed_checks)


def test_general_matrices_take_the_exact_path():
    """(A, G) not in SDC form: no Newton–Kleinman, scipy and the general checks, same answer."""
    rng = np.random.default_rng(8)
    A = rng.normal(size=(N, 4, 4))
    G = rng.normal(size=(N, 4, 2))
    Q, R = np.eye(4), np.eye(2)
    fast, ref = SdreController(Q, R, 10.0, n=N), SdreController(Q, R, 10.0, n=N, method='reference')
    for _ in range(3):
        a, b = (fast.step(A, G, np.ones((N, 4)), np.zeros((N, 4))),
                ref.step(A, G, np.ones((N, 4)), np.zeros((N, 4))))
        np.testing.assert_array_equal(a.u, b.u)
        assert np.all(a.nk_iterations == 0)
    assert fast.exact_solves == 3 * N


def test_fast_is_faster_than_the_reference_in_the_same_run(model):
    pos, vel, ref, ref_vel = trajectory_states(model, 60, (5e-5, 5e-3), seed=9)

    def median_step(method):
        c = SdreLaw(model, Weights(**DEFAULT_WEIGHTS), 0.0625, method=method)
        times = []
        for k in range(len(pos)):
            t0 = time.perf_counter()
            c.compute(pos[k], vel[k], ref[k], ref_vel[k])
            times.append(time.perf_counter() - t0)
        return float(np.median(times[1:]))
    fast, reference = median_step('fast'), median_step('reference')
    assert fast * 3.0 < reference, (fast, reference)
