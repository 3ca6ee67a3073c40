"""The compiled kernels against the numpy fast path and the scipy reference, at their public APIs.

The kernels run the numpy fast path's algorithm (same warm start, stop rule and checks), so they
are held to it tightly (``SAME_TOL`` of the largest torque: only the summation order differs) and
to the reference within the fast path's stated tolerance (``U_TOL``, as in test_sdre_fast.py).
The supervisor part that is not compiled (the exact path for the fingers the kernel hands back)
is KernelLaw's: SdreController's exact path, run by a cold one-finger controller.
"""
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
from soft_gripper_sdre.control import compiled
from soft_gripper_sdre.control.compiled import (SdcNetwork, SdreOutputs, SdreSettings, SdreState, kf_step,
                                                model_inversion, sdc_forward, sdre_step, warm_up)
from soft_gripper_sdre.control import compiled_sdre
from soft_gripper_sdre.control.kf import ConstantVelocityKF
from soft_gripper_sdre.control.laws import make_law, model_inversion as numpy_model_inversion
from soft_gripper_sdre.control.sdre import Check, SdreController, care
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, TrackingController, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.bench_kernel import KernelLaw

U_TOL = 1e-4
SAME_TOL = 1e-9
N = 4
U_MAX = 0.0625
ROOT = Path(__file__).resolve().parents[1]


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
    return run_closed_loop(model, duration=0.6, weights=weights, u_max=U_MAX, profile=profile,
                           sim_config=SimConfig(scene='hand', noise_std=request.param))


def replay(law, loop, **kw):
    return [law.compute(loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k], loop.ref_vel[k], **kw)
            for k in range(len(loop.est))]


def test_check_bits_are_those_of_sdre_check():
    for name in ('STABILIZABLE', 'HURWITZ', 'ACL_SINGULAR', 'SOLVE_FAILED', 'NONFINITE', 'RESIDUAL', 'P_NOT_PD'):
        assert getattr(compiled_sdre, name) == int(Check[name])


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


def test_tracking_law_equals_the_numpy_fast_path_and_the_reference(model, weights, loop):
    kernel = KernelLaw(model, weights, U_MAX)
    fast = TrackingController(model, weights, U_MAX, method='fast', lowpass_hz=0.0)
    ref = TrackingController(model, weights, U_MAX, method='reference', lowpass_hz=0.0)
    out_k, out_f, out_r = replay(kernel, loop), replay(fast, loop), replay(ref, loop)
    uk = np.array([o['u_unsat'] for o in out_k])
    uf, ur = (np.array([o.u_unsat for o in outs]) for outs in (out_f, out_r))
    scale = np.abs(ur).max()
    assert scale > 1e-3                                             # the law does something
    np.testing.assert_allclose(uk, ur, rtol=0, atol=U_TOL * scale)
    np.testing.assert_allclose(uk, uf, rtol=0, atol=SAME_TOL * scale)
    np.testing.assert_array_equal(np.array([o['u'] for o in out_k]), np.clip(uk, -U_MAX, U_MAX))
    for o_k, o_f, o_r in zip(out_k, out_f, out_r):
        assert o_k['ok'].all() and o_r.ok.all() and not o_k['failed_checks'].any()
        for name in ('K', 'Ks'):
            np.testing.assert_allclose(o_k[name], getattr(o_r, name), rtol=0,
                                       atol=U_TOL * np.abs(getattr(o_r, name)).max())
        # P's position block is weakly determined (the velocity weight is zero): on noisy states the
        # numpy fast path's P, and so the kernel's, can differ from scipy's by more than U_TOL of its
        # largest entry there; the gains, which see P only through its lower rows, stay within U_TOL
        np.testing.assert_allclose(o_k['P'], o_r.P, rtol=0, atol=10 * U_TOL * np.abs(o_r.P).max())
        np.testing.assert_allclose(o_k['P'], o_f.P, rtol=0, atol=SAME_TOL * np.abs(o_f.P).max())
        assert np.all(o_k['residual'] < 1e-6)
    # the same iterations as the numpy fast path, and exact solves only for the cold start
    its_k = np.array([o['nk_iterations'] for o in out_k[1:]])
    its_f = np.array([o.nk_iterations for o in out_f[1:]])
    assert its_k.min() >= 1 and abs(its_k.mean() - its_f.mean()) <= 0.02
    assert kernel.exact_solves == N == fast.sdre.exact_solves


@pytest.mark.parametrize('ff_at', ['x', 'ref'])
def test_feedforward_law_equals_the_numpy_law_and_the_reference(model, weights, loop, ff_at):
    acc = np.gradient(loop.ref_vel, 1e-3, axis=0)                  # a moving reference's acceleration
    kernel = KernelLaw(model, weights, U_MAX, law='sdre_ff', ff_at=ff_at)
    fast, ref = (make_law('sdre_ff', model, weights, U_MAX, method=m, lowpass_hz=0.0, ff_at=ff_at)
                 for m in ('fast', 'reference'))
    outs = {}
    for name, law in (('kernel', kernel), ('fast', fast), ('ref', ref)):
        outs[name] = [law.compute(loop.est[k, :, :2], loop.est[k, :, 2:], loop.ref_pos[k], loop.ref_vel[k],
                                  ref_acc=acc[k]) for k in range(len(acc))]
    uk = np.array([o['u_unsat'] for o in outs['kernel']])
    uf, ur = (np.array([o.u_unsat for o in outs[m]]) for m in ('fast', 'ref'))
    scale = np.abs(ur).max()
    np.testing.assert_allclose(uk, ur, rtol=0, atol=U_TOL * scale)
    np.testing.assert_allclose(uk, uf, rtol=0, atol=SAME_TOL * scale)
    for o_k, o_r in zip(outs['kernel'], outs['ref']):
        for name in ('ok', 'fallback', 'failed_checks'):
            np.testing.assert_array_equal(o_k[name], getattr(o_r, name))


def test_feedforward_faults_match_the_numpy_law(model, weights):
    """A NaN state (solved at zero, no torque), a NaN reference acceleration (no a_d, flagged)."""
    kernel = KernelLaw(model, weights, U_MAX, law='sdre_ff')
    fast = make_law('sdre_ff', model, weights, U_MAX, method='fast', lowpass_hz=0.0)
    rest = np.tile(model.rest_tip[:2], (N, 1))
    pos, vel, ref = rest + 1e-3, np.full((N, 2), 0.01), rest + 2e-3
    acc = np.full((N, 2), 0.5)
    for _ in range(2):                                              # cold, then warm
        kernel.compute(pos, vel, ref, np.zeros((N, 2)), ref_acc=acc)
        fast.compute(pos, vel, ref, np.zeros((N, 2)), ref_acc=acc)
    pos[1, 0], acc[2, 1] = np.nan, np.inf
    k = kernel.compute(pos, vel, ref, np.zeros((N, 2)), ref_acc=acc)
    f = fast.compute(pos, vel, ref, np.zeros((N, 2)), ref_acc=acc)
    for name in ('ok', 'fallback', 'failed_checks', 'saturated'):
        expected = getattr(f, name)
        got = k[name] if name != 'saturated' else np.abs(k['u_unsat']) > U_MAX
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_allclose(k['u_unsat'], f.u_unsat, rtol=0, atol=SAME_TOL * np.abs(f.u_unsat).max())
    assert np.all(k['u'][1] == 0.0) and list(k['fallback']) == [False, True, True, False]


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
# the checks: the fault cases of test_sdre_fast.py
# ----------------------------------------------------------------------------------------------

def sdc_plant(model, seed):
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.uniform(-3e-3, 3e-3, (N, 2)), rng.uniform(-0.02, 0.02, (N, 2))], axis=1)
    a, g = model.sdc_blocks(x)
    return x, a.copy(), g.copy()


def full(a, g):
    """A = [[0, I], a], G = [[0], g]."""
    A = np.zeros((len(a), 4, 4))
    A[:, 0, 2] = A[:, 1, 3] = 1.0
    A[:, 2:, :] = a
    G = np.zeros((len(a), 4, 2))
    G[:, 2:, :] = g
    return A, G


def kernel_and_numpy(model, weights):
    return KernelLaw(model, weights, U_MAX), SdreController(weights.Q, weights.R, U_MAX, n=N)


def test_faults_give_the_numpy_fast_paths_checks_fallbacks_and_torques(model, weights):
    """Singular G2 (not stabilisable), NaN from the model, an infinite state: the same Check bits,
    fallbacks to the last valid gains, zero torque for the unreadable state; then the cold restart
    (exact solve) and the return to Newton–Kleinman, finger by finger as on the numpy path."""
    x, a, g = sdc_plant(model, 4)
    kernel, numpy_fast = kernel_and_numpy(model, weights)
    zero = np.zeros((N, 4))
    for _ in range(2):
        good = kernel.step_sdc(a, g, x, zero)
        numpy_fast.step_sdc(a, g, x, zero)
    g_bad, a_bad, x_bad = g.copy(), a.copy(), x.copy()
    g_bad[0, 1] = g_bad[0, 0] * 3.0                  # rank 1
    a_bad[1, 0, 2] = np.nan
    x_bad[2, 3] = np.inf
    sequence = [(a_bad, g_bad, x_bad), (a, g, x), (a, g, x)]
    for step, (a_k, g_k, x_k) in enumerate(sequence):
        k = kernel.step_sdc(a_k, g_k, x_k, zero)
        f = numpy_fast.step_sdc(a_k, g_k, x_k, zero)
        for name in ('failed_checks', 'ok', 'fallback'):
            np.testing.assert_array_equal(k[name], getattr(f, name), err_msg=f'step {step}: {name}')
        np.testing.assert_array_equal(k['nk_iterations'] == 0, f.nk_iterations == 0)
        np.testing.assert_allclose(k['u'], f.u, rtol=0, atol=SAME_TOL * np.abs(f.u).max())
        assert np.isfinite(k['u']).all()
        if step == 0:
            assert k['failed_checks'][0] & Check.STABILIZABLE and k['failed_checks'][1] & Check.NONFINITE
            assert k['failed_checks'][2] & Check.NONFINITE and np.all(k['u'][2] == 0.0)
            np.testing.assert_array_equal(k['K'][:3], good['K'][:3])        # the last valid gains
    assert kernel.exact_solves == numpy_fast.exact_solves


def test_anti_stabilising_and_garbage_warm_starts_are_rejected_then_solved_exactly(model, weights):
    """Warm starts at the ARE's anti-stabilising solution (a fixed point of Newton's iteration), at
    a random symmetric matrix, at NaN and at 1e30: the kernel's checks reject each, the exact path
    solves it, and the gains equal the reference's."""
    x, a, g = sdc_plant(model, 2)
    zero = np.zeros((N, 4))
    A, G = full(a, g)
    anti = np.stack([-care(-A[i], G[i], weights.Q, weights.R) for i in range(N)])
    E = np.random.default_rng(1).normal(size=(N, 4, 4))
    starts = {'anti-stabilising': anti, 'random': E + E.transpose(0, 2, 1), 'nan': np.full((N, 4, 4), np.nan),
              'huge': np.full((N, 4, 4), 1e30)}
    ref = SdreController(weights.Q, weights.R, U_MAX, n=N, method='reference').step_sdc(a, g, x, zero)
    for name, P0 in starts.items():
        kernel = KernelLaw(model, weights, U_MAX)
        kernel.step_sdc(a, g, x, zero)                           # cold start: exact
        kernel.state.P[:] = P0
        state, out = SdreState(*(s.copy() for s in kernel.state)), SdreOutputs.empty(N)
        out.a2[:], out.g2[:] = a, g
        sdre_step(x, zero, *kernel.settings, *state, *out)
        assert not state.warm.any() and out.failed.all(), name   # every finger rejected, with a reason
        if name == 'anti-stabilising':
            assert np.all(out.residual < 1e-6) and np.all(out.failed & (Check.P_NOT_PD | Check.HURWITZ))
        assert np.isfinite(out.u).all()
        k = kernel.step_sdc(a, g, x, zero)                       # the same step with the exact path
        assert k['ok'].all() and not k['failed_checks'].any() and np.all(k['nk_iterations'] == 0), name
        np.testing.assert_allclose(k['K'], ref.K, rtol=1e-9, err_msg=name)
        assert kernel.step_sdc(a, g, x, zero)['nk_iterations'].min() >= 1      # and back to Newton–Kleinman


def test_singular_closed_loop_block_is_flagged(model, weights):
    """ACL_SINGULAR is cond(C) ≥ cond_max for A_cl = [[0, I], [C, ·]], C from the returned P."""
    x, a, g = sdc_plant(model, 6)
    zero = np.zeros((N, 4))
    kernel = KernelLaw(model, weights, U_MAX)
    kernel.step_sdc(a, g, x, zero)
    P = kernel.state.P.copy()
    W = g @ np.linalg.inv(weights.R) @ g.transpose(0, 2, 1)
    C = a[:, :, :2] - (W @ P[:, 2:, :])[:, :, :2]
    cond_C, cond_G = np.linalg.cond(C), np.linalg.cond(g)
    for i in range(N):
        assert cond_G[i] < cond_C[i], 'a limit between them must trip the A_cl test alone'  # (this model)
        limit = np.sqrt(cond_G[i] * cond_C[i])
        settings = SdreSettings.of(weights.Q, weights.R, U_MAX, cond_max=limit)
        state, out = SdreState(*(s.copy() for s in kernel.state)), SdreOutputs.empty(N)
        out.a2[:], out.g2[:] = a, g
        sdre_step(x, zero, *settings, *state, *out)
        expected = cond_C >= limit
        np.testing.assert_array_equal(out.failed & Check.ACL_SINGULAR != 0, expected)
        np.testing.assert_array_equal(state.warm, ~expected)


def test_overflowing_torque_is_zeroed_like_the_numpy_path(model, weights):
    x, a, g = sdc_plant(model, 8)
    kernel, numpy_fast = kernel_and_numpy(model, weights)
    zero = np.zeros((N, 4))
    for _ in range(2):
        kernel.step_sdc(a, g, x, zero)
        numpy_fast.step_sdc(a, g, x, zero)
    x_big = x.copy()
    x_big[1] = 1e305                                             # finite, but K x overflows
    k, f = kernel.step_sdc(a, g, x_big, zero), numpy_fast.step_sdc(a, g, x_big, zero)
    np.testing.assert_array_equal(k['u_unsat'][1], f.u_unsat[1])
    np.testing.assert_allclose(k['u'], f.u, rtol=0, atol=SAME_TOL * np.abs(f.u).max())


# ----------------------------------------------------------------------------------------------
# the Kalman filter, compilation
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize('process_noise', ['independent', 'paper'])
def test_kf_step_equals_constant_velocity_kf(process_noise):
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
        kf_step(x, P, z, valid, kf.F, kf.Q, kf.R)
        x_ref = kf.step(z, valid)
        np.testing.assert_allclose(x, x_ref, rtol=1e-12, atol=1e-12 * np.abs(x_ref).max())
        np.testing.assert_allclose(P, kf.P, rtol=1e-12, atol=1e-12 * np.abs(kf.P).max())


def test_warm_up_leaves_one_signature_per_kernel_and_a_replay_adds_none(model, weights):
    kernels = [compiled.sdc_forward, compiled.sdre_gains, compiled.tracking_torques, compiled.sdre_step,
               compiled.model_inversion, compiled.tracking_step, compiled.feedforward_step, compiled.kf_step]
    warm_up()
    before = [len(k.signatures) for k in kernels]
    assert before == [1] * len(kernels)
    law = KernelLaw(model, weights, U_MAX, law='sdre_ff')
    rest = np.tile(model.rest_tip[:2], (N, 1))
    for k in range(3):
        law.compute(rest + 1e-3 * k, np.zeros((N, 2)), rest, np.zeros((N, 2)), ref_acc=np.ones((N, 2)))
    assert [len(k.signatures) for k in kernels] == before


@pytest.mark.slow
def test_warm_up_compiles_once_then_loads_from_the_cache(tmp_path):
    """Two fresh interpreters with one numba cache directory: the first compiles every kernel, the
    second loads every one of them from the cache (no compilation)."""
    code = ('from soft_gripper_sdre.control import compiled as c; c.warm_up(); '
            'ks = [c.sdc_forward, c.sdre_gains, c.tracking_torques, c.sdre_step, c.model_inversion, '
            'c.tracking_step, c.feedforward_step, c.kf_step]; '
            'print(sum(len(k.stats.cache_misses) for k in ks), sum(sum(k.stats.cache_hits.values()) for k in ks))')
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), PYTHONPATH=str(ROOT))
    runs = [subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, check=True,
                           timeout=600).stdout.split() for _ in range(2)]
    (miss1, hit1), (miss2, hit2) = ([int(v) for v in r] for r in runs)
    assert miss1 >= 8 and hit1 == 0
    assert miss2 == 0 and hit2 >= 8


def test_bench_kernel_reports_every_path(capsys):
    from soft_gripper_sdre.tools.bench_kernel import main
    assert main(['--seconds', '0.05', '--no-compile-times']) == 0
    out = capsys.readouterr().out
    for row in ('numpy fast', 'compiled (KernelLaw)', 'compiled kernel call', 'scipy reference', 'KF step'):
        assert row in out
    assert out.count('exact solves: 4 compiled, 4 numpy') == 2          # cold start only, both laws
