"""The compiled kernels at their own interfaces and through the laws, against the scipy reference.

Through the laws (the fast path: the kernels under SdreController) the torques agree with the
reference to ``U_TOL`` of the largest, as in test_sdre_fast.py, here along clean and noisy
closed-loop replays; the kernels' own pieces (network, model inversion, Kalman filter) are held to
numpy evaluations of the same formulas to rounding.
"""
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
from soft_gripper_sdre.control import kernels as compiled
from soft_gripper_sdre.control.kernels import (
    SdcNetwork,
    SdreOutputs,
    SdreSettings,
    kf_step,
    model_inversion,
    sdc_forward,
    sdre_step,
    warm_up,
)
from soft_gripper_sdre.control.kernels import riccati as compiled_riccati
from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.laws import model_inversion as numpy_model_inversion
from soft_gripper_sdre.control.riccati import Check, care, full_sdc_matrices
from soft_gripper_sdre.control.sdre import SdreController
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.sim.hand import SimConfig

U_TOL = 1e-4
N = 4
U_MAX = 0.0625
ROOT = Path(__file__).resolve().parents[1]
KERNELS = ('sdc_forward', 'sdre_gains', 'tracking_torques', 'sdre_step', 'model_inversion',
           'tracking_step', 'feedforward_step', 'kf_step')


@pytest.fixture(scope='module')
def model():
    warm_up()
    return SDCModel()


@pytest.fixture(scope='module')
def weights():
    return Weights(**DEFAULT_WEIGHTS)


@pytest.fixture(scope='module', params=[0.0, 5e-5], ids=['clean', 'noisy'])
def loop(request, model, weights):
    """A short in-process grasp (fingers moving from 50 ms on), its estimates to replay."""
    profile = GraspProfile(t_start=0.05, t_close=0.4, t_hold=0.1, others='open')
    return run_closed_loop(make_law('sdre', model, weights, U_MAX), duration=0.6, profile=profile,
                           sim_config=SimConfig(scene='hand', noise_std=request.param))


def replay(law, loop, acc=None):
    return [law.compute(loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k], loop.ref_vel[k],
                        ref_acc=None if acc is None else acc[k]) for k in range(len(loop.est))]


def fast_and_reference(law, model, weights, **options):
    return [make_law(law, model, weights, U_MAX, method=m, lowpass_hz=0.0, **options)
            for m in ('fast', 'reference')]


def test_check_bits_are_those_of_riccati_check():
    for name in ('STABILIZABLE', 'HURWITZ', 'ACL_SINGULAR', 'SOLVE_FAILED', 'NONFINITE', 'RESIDUAL',
                 'P_NOT_PD'):
        assert getattr(compiled_riccati, name) == int(Check[name])


def test_network_equals_the_numpy_model(model):
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-8e-3, 8e-3, (16, 2)), rng.uniform(-0.1, 0.1, (16, 2))], axis=1)
    a2, g2 = np.zeros((16, 2, 4)), np.zeros((16, 2, 2))
    sdc_forward(x, *SdcNetwork.of(model), a2, g2)
    a_ref, g_ref = model.sdc_blocks(x)
    np.testing.assert_allclose(a2, a_ref, rtol=1e-12, atol=1e-12 * np.abs(a_ref).max())
    np.testing.assert_allclose(g2, g_ref, rtol=1e-12, atol=1e-12 * np.abs(g_ref).max())
    x[3, 1] = np.nan                                   # a non-finite state gives non-finite blocks
    sdc_forward(x, *SdcNetwork.of(model), a2, g2)
    assert not np.isfinite(a2[3]).all() and np.isfinite(a2[[0, 1, 2, 4]]).all()


# ----------------------------------------------------------------------------------------------
# the laws on the fast path against the reference
# ----------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.timeout(240)
def test_sdre_law_equals_the_reference_along_a_closed_loop(model, weights, loop):
    fast, ref = fast_and_reference('sdre', model, weights)
    out_f, out_r = replay(fast, loop), replay(ref, loop)
    uf, ur = (np.array([o.u_unsat for o in outs]) for outs in (out_f, out_r))
    scale = np.abs(ur).max()
    assert scale > 1e-3                                             # the law does something
    np.testing.assert_allclose(uf, ur, rtol=0, atol=U_TOL * scale)
    np.testing.assert_array_equal(np.array([o.u for o in out_f]), np.clip(uf, -U_MAX, U_MAX))
    for o_f, o_r in zip(out_f, out_r):
        assert o_f.ok.all() and o_r.ok.all() and not o_f.failed_checks.any()
        for name in ('K', 'Ks'):
            np.testing.assert_allclose(getattr(o_f, name), getattr(o_r, name), rtol=0,
                                       atol=U_TOL * np.abs(getattr(o_r, name)).max())
        # P's position block is weakly determined (the velocity weight is zero): on noisy states the
        # kernel's P can differ from scipy's by more than U_TOL of its largest entry there; the
        # gains, which see P only through its lower rows, stay within U_TOL
        np.testing.assert_allclose(o_f.P, o_r.P, rtol=0, atol=10 * U_TOL * np.abs(o_r.P).max())
        assert np.all(o_f.residual < 1e-6)
    # Newton–Kleinman on every step after the cold start, which alone is solved exactly
    assert np.array([o.nk_iterations for o in out_f[1:]]).min() >= 1
    assert fast.sdre.exact_solves == N and fast.sdre.steps == len(out_f)


@pytest.mark.slow
@pytest.mark.timeout(240)
@pytest.mark.parametrize('ff_at', ['x', 'ref'])
def test_feedforward_law_equals_the_reference_along_a_closed_loop(model, weights, loop, ff_at):
    acc = np.gradient(loop.ref_vel, 1e-3, axis=0)  # a moving reference's acceleration
    fast, ref = fast_and_reference('sdre_ff', model, weights, ff_at=ff_at)
    out_f, out_r = replay(fast, loop, acc), replay(ref, loop, acc)
    uf, ur = (np.array([o.u_unsat for o in outs]) for outs in (out_f, out_r))
    np.testing.assert_allclose(uf, ur, rtol=0, atol=U_TOL * np.abs(ur).max())
    for o_f, o_r in zip(out_f, out_r):
        for name in ('ok', 'fallback', 'failed_checks', 'saturated'):
            np.testing.assert_array_equal(getattr(o_f, name), getattr(o_r, name))
    assert fast.sdre.exact_solves == N


def test_feedforward_faults_match_the_reference(model, weights):
    """A NaN state (solved at zero, no torque), a NaN reference acceleration (no a_d, flagged)."""
    fast, ref = fast_and_reference('sdre_ff', model, weights)
    rest = np.tile(model.rest_tip[:2], (N, 1))
    pos, vel, ref_pos = rest + 1e-3, np.full((N, 2), 0.01), rest + 2e-3
    acc = np.full((N, 2), 0.5)
    for _ in range(2):                                              # cold, then warm
        for law in (fast, ref):
            law.compute(pos, vel, ref_pos, np.zeros((N, 2)), ref_acc=acc)
    pos[1, 0], acc[2, 1] = np.nan, np.inf
    f, r = (law.compute(pos, vel, ref_pos, np.zeros((N, 2)), ref_acc=acc) for law in (fast, ref))
    for name in ('ok', 'fallback', 'failed_checks', 'saturated'):
        np.testing.assert_array_equal(getattr(f, name), getattr(r, name))
    np.testing.assert_allclose(f.u_unsat, r.u_unsat, rtol=0, atol=U_TOL * np.abs(r.u_unsat).max())
    assert np.all(f.u[1] == 0.0) and list(f.fallback) == [False, True, True, False]
    # the finger with the NaN state was solved at zero and stays warm: Newton–Kleinman next step
    pos[1, 0] = rest[1, 0] + 1e-3
    assert fast.compute(pos, vel, ref_pos, np.zeros((N, 2)), ref_acc=acc).nk_iterations.min() >= 1


def test_bench_times_the_compiled_laws_against_the_reference(loop):
    """tools/benchmarks/bench_compute's controller rows: both laws replayed, the reference on the
    paired steps, the torques compared there."""
    from soft_gripper_sdre.tools.benchmarks.bench_compute import bench_control, bench_kf
    for law in ('sdre', 'sdre_ff'):
        r = bench_control(loop, law, repeats=1, ref_steps=10)
        assert all(r[k] > 0 for k in ('fast', 'fast_paired', 'reference', 'kernel'))
        assert r['iterations'] >= 1 and r['exact'] == 0.0 and r['difference'] < U_TOL
    assert bench_kf(loop, repeats=1) > 0


def test_model_inversion_equals_the_numpy_function(model):
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-3e-3, 3e-3, (N, 2)), rng.uniform(-0.02, 0.02, (N, 2))], axis=1)
    a2, g2 = (b.copy() for b in model.sdc_blocks(x))
    g2[2, 1] = 2.0 * g2[2, 0]                                       # singular: no feedforward
    a2[3, 0, 0] = np.nan
    a_d = rng.normal(size=(N, 2))
    u, usable = np.zeros((N, 2)), np.zeros(N, dtype=np.bool_)
    model_inversion(a2, g2, x, a_d, 1e8, u, usable)
    u_ref, usable_ref = numpy_model_inversion(a2, g2, x, a_d)
    np.testing.assert_array_equal(usable, usable_ref)
    np.testing.assert_allclose(u, u_ref, rtol=1e-10, atol=0)


# ----------------------------------------------------------------------------------------------
# the kernel's checks
# ----------------------------------------------------------------------------------------------

def sdc_plant(model, seed):
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.uniform(-3e-3, 3e-3, (N, 2)), rng.uniform(-0.02, 0.02, (N, 2))], axis=1)
    a, g = model.sdc_blocks(x)
    return x, a.copy(), g.copy()


def solved_state(weights, a, g, x):
    """The state a fast controller holds after one (exact) step on the plant, and its settings."""
    ctrl = SdreController(weights.Q, weights.R, U_MAX, n=N)
    assert ctrl.step_sdc(a, g, x, np.zeros((N, 4))).ok.all()
    return ctrl.state, ctrl.settings


def kernel_step(state, settings, a, g, x):
    """sdre_step from a copy of ``state``: (the state after it, its outputs)."""
    state, out = state.copy(), SdreOutputs(N)
    out.a2[:], out.g2[:] = a, g
    sdre_step(x, np.zeros((N, 4)), settings.records, state.records, out.records)
    return state, out


def test_anti_stabilising_and_garbage_warm_starts_are_rejected_then_solved_from_scratch(model,
                                                                                      weights):
    """Warm starts at the ARE's anti-stabilising solution (a fixed point of Newton's iteration),
    at a random symmetric matrix, at NaN and at 1e30: Newton–Kleinman from each fails the checks,
    and the kernel solves the finger again from scratch (the Hamiltonian's sign function, then
    Newton–Kleinman) to the reference's gains, without the exact path."""
    x, a, g = sdc_plant(model, 2)
    zero = np.zeros((N, 4))
    A, G = full_sdc_matrices(a, g)
    anti = np.stack([-care(-A[i], G[i], weights.Q, weights.R) for i in range(N)])
    E = np.random.default_rng(1).normal(size=(N, 4, 4))
    starts = {'anti-stabilising': anti, 'random': E + E.transpose(0, 2, 1),
              'nan': np.full((N, 4, 4), np.nan), 'huge': np.full((N, 4, 4), 1e30)}
    ref = SdreController(weights.Q, weights.R, U_MAX, n=N,
                         method='reference').step_sdc(a, g, x, zero)
    state, settings = solved_state(weights, a, g, x)
    for name, P0 in starts.items():
        start = state.copy()
        start.P[:] = P0
        after, out = kernel_step(start, settings, a, g, x)
        assert after.warm.all() and not out.failed.any(), name
        assert np.all(out.residual < 1e-9), name
        np.testing.assert_allclose(after.K, ref.K, rtol=1e-8, err_msg=name)
        ctrl = SdreController(weights.Q, weights.R, U_MAX, n=N)
        ctrl.warm_start(P0)
        k = ctrl.step_sdc(a, g, x, zero)
        assert k.ok.all() and not k.failed_checks.any() and ctrl.exact_solves == 0, name
        assert np.all(k.nk_iterations >= 1), name
        np.testing.assert_allclose(k.K, ref.K, rtol=1e-8, err_msg=name)


def test_a_finger_the_restart_cannot_solve_keeps_its_gains_and_ends_cold(model, weights):
    """With a residual tolerance nothing meets, Newton–Kleinman and the solve from scratch both
    fail the checks: the finger ends cold (for the supervisor's exact path), with the reason,
    and the gains in use are kept."""
    x, a, g = sdc_plant(model, 2)
    A, G = full_sdc_matrices(a, g)
    anti = np.stack([-care(-A[i], G[i], weights.Q, weights.R) for i in range(N)])
    state, settings = solved_state(weights, a, g, x)
    settings = settings.copy()
    settings.residual_tol[0] = 0.0
    start = state.copy()
    start.P[:] = anti
    after, out = kernel_step(start, settings, a, g, x)
    assert not after.warm.any() and np.all(out.failed & Check.RESIDUAL)
    assert np.all(out.iterations >= 1)
    np.testing.assert_array_equal(after.K, state.K)
    assert np.isfinite(out.u).all()


def test_singular_closed_loop_block_is_flagged(model, weights):
    """ACL_SINGULAR is cond(C) ≥ cond_max for A_cl = [[0, I], [C, ·]], C from the returned P."""
    x, a, g = sdc_plant(model, 6)
    state, _ = solved_state(weights, a, g, x)
    W = g @ np.linalg.inv(weights.R) @ g.transpose(0, 2, 1)
    C = a[:, :, :2] - (W @ state.P[:, 2:, :])[:, :, :2]
    cond_C, cond_G = np.linalg.cond(C), np.linalg.cond(g)
    for i in range(N):
        assert cond_G[i] < cond_C[i], (
            'a limit between them must trip the A_cl test alone')  # (this model)
        limit = np.sqrt(cond_G[i] * cond_C[i])
        after, out = kernel_step(state, SdreSettings.of(weights.Q, weights.R, U_MAX,
                                                        cond_max=limit), a, g, x)
        expected = cond_C >= limit
        np.testing.assert_array_equal(out.failed & Check.ACL_SINGULAR != 0, expected)
        np.testing.assert_array_equal(after.warm, ~expected)


def test_overflowing_torque_is_zeroed_like_the_reference(model, weights):
    x, a, g = sdc_plant(model, 8)
    fast, ref = (SdreController(weights.Q, weights.R, U_MAX, n=N, method=m)
                 for m in ('fast', 'reference'))
    zero = np.zeros((N, 4))
    for _ in range(2):
        K = fast.step_sdc(a, g, x, zero).K
        ref.step_sdc(a, g, x, zero)
    x_big = x.copy()
    x_big[1] = np.finfo(float).max * np.sign(K[1, 0])           # finite, but K x overflows
    f, r = fast.step_sdc(a, g, x_big, zero), ref.step_sdc(a, g, x_big, zero)
    assert f.ok.all() and np.all(f.u_unsat[1, 0] == 0.0) and np.all(r.u_unsat[1, 0] == 0.0)
    np.testing.assert_allclose(f.u, r.u, rtol=0, atol=U_TOL * np.abs(r.u).max())


# ----------------------------------------------------------------------------------------------
# the Kalman filter, compilation
# ----------------------------------------------------------------------------------------------

def numpy_kf_step(x, P, z, valid, F, Q, R):
    """The yardstick: predict, then the Joseph-form update where ``valid`` and z is finite."""
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    x, P = x @ F.T, F @ P @ F.T + Q
    for i in np.flatnonzero(valid & np.isfinite(z).all(axis=1)):
        K = P[i] @ H.T @ np.linalg.inv(H @ P[i] @ H.T + R)
        x[i] = x[i] + K @ (z[i] - H @ x[i])
        IKH = np.eye(4) - K @ H
        P[i] = IKH @ P[i] @ IKH.T + K @ R @ K.T
    return x, P


@pytest.mark.parametrize('process_noise', ['independent', 'paper'])
def test_kalman_filter_equals_the_numpy_equations(process_noise):
    rng = np.random.default_rng(9)
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=N, process_noise=process_noise)
    z0 = rng.normal(size=(N, 2)) * 1e-2
    kf.reset(z0)
    x, P = kf.x.copy(), kf.P.copy()
    t = np.arange(1, 600) * 1e-3
    for k, tk in enumerate(t):
        z = z0 + 1e-2 * np.sin(2 * np.pi * 2.0 * tk) + 5e-5 * rng.normal(size=(N, 2))
        valid = np.ones(N, dtype=np.bool_)
        if k % 97 == 5:
            valid[k % N] = False                                  # a lost measurement
        if k % 131 == 7:
            z[(k + 1) % N, 0] = np.nan                            # a non-finite one
        x, P = numpy_kf_step(x, P, z, valid, kf.F, kf.Q, kf.R)
        estimate = kf.step(z, valid)
        np.testing.assert_allclose(estimate, x, rtol=1e-12, atol=1e-12 * np.abs(x).max())
        np.testing.assert_allclose(kf.P, P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    x_copy = kf.x.copy()                                          # the bare kernel, in place
    kf_step(x_copy, kf.P.copy(), np.zeros((N, 2)), np.zeros(N, dtype=np.bool_), kf.F, kf.Q, kf.R)
    np.testing.assert_allclose(x_copy, kf.x @ kf.F.T, rtol=1e-15)


def test_warm_up_leaves_one_signature_per_kernel_and_the_laws_add_none(model, weights):
    kernels = [getattr(compiled, name) for name in KERNELS]
    warm_up()
    before = [len(k.signatures) for k in kernels]
    assert before == [1] * len(kernels)
    rest = np.tile(model.rest_tip[:2], (N, 1))
    laws = [make_law(name, model, weights, U_MAX, ff_at=ff_at) for name, ff_at in
            (('sdre', None), ('sdre_ff', 'x'), ('sdre_ff', 'ref'))]
    kf = ConstantVelocityKF(1e-3, 1.0, 5e-5, n=N)
    read_only = np.frombuffer(rest.tobytes(), dtype=float).reshape(N, 2)     # as a decoded message
    for k in range(3):
        for law in laws:  # lists, views, read-only buffers, as nodes hand them over
            law.compute((rest + 1e-3 * k).tolist(), np.zeros((N, 4))[:, 1:3], read_only,
                        np.zeros((N, 2)), ref_acc=read_only)
        kf.step((rest + 1e-3 * k)[:, ::-1], np.ones(N))
        kf.step(read_only, np.ones(N, dtype=bool)[::-1])
    SdreController(weights.Q, weights.R, U_MAX, n=N).step_sdc(
        *model.sdc_blocks(np.zeros((N, 4))), np.zeros((N, 4)), np.zeros((N, 4)).tolist())
    assert [len(k.signatures) for k in kernels] == before


@pytest.mark.timeout(120)
def test_a_fresh_interpreter_loads_every_kernel_from_the_cache():
    """The cache the session filled before its first test (conftest, as ``make kernels`` does): a
    fresh interpreter's warm_up compiles no kernel and loads every one of them from it."""
    code = ('from soft_gripper_sdre.control import kernels as c; c.warm_up(); '
            f'ks = [getattr(c, name) for name in {KERNELS!r}]; '
            'print(sum(len(k.stats.cache_misses) for k in ks), '
            'sum(sum(k.stats.cache_hits.values()) for k in ks))')
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         check=True, timeout=110)
    misses, hits = (int(v) for v in run.stdout.split())
    assert misses == 0 and hits >= len(KERNELS)
