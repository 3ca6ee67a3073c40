"""The general kernels (control/kernels/general.py) against the numpy general path, for the finger
shapes of test/shaped_models.py: the same torques, gains, checks and flags step by step along
closed loops on the model, the bounds held, non-finite inputs answered with finite commands inside
the bounds, and no compilation after warm_up."""
import numpy as np
import pytest
from shaped_models import INPUT_MAPS, REST, ShapedModel, input_signal, model_reference, rk4

from soft_gripper_sdre.control import kernels
from soft_gripper_sdre.control.kernels import general
from soft_gripper_sdre.control.laws import SdreFeedforwardLaw, SdreLaw
from soft_gripper_sdre.control.riccati import Check
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

W = Weights(q_pos=1e6, q_vel=0.0, r=1.6e4)
U_MAX = 0.05
#: the shapes and bounds of the tests: (2, 2) with one one-sided input takes the general path too
CASES = {
    (2, 1): InputBounds([0.0], [U_MAX]),
    (2, 2): InputBounds([0.0, -U_MAX], [U_MAX, U_MAX]),
    (3, 3): InputBounds([0.0, 0.0, 0.0], [U_MAX] * 3),
    (3, 2): InputBounds.symmetric(U_MAX, 2),
    (2, 3): InputBounds([0.0, -U_MAX, 0.0], [U_MAX, U_MAX, 0.3]),
    (2, 4): InputBounds([0.0] * 4, [U_MAX] * 4),
}
#: the compiled path's torques against numpy's, relative to the largest |u_unsat| of the step
U_RTOL = 1e-7
DT = 1e-3


class FusedShapedModel(ShapedModel):
    """A :class:`ShapedModel`-like SDC model of shape (d, m) given by a fused network
    (``fused_network``, as SDCModel has), evaluated in numpy by :meth:`sdc_blocks`: the blocks
    at rest are ShapedModel's (stiffness, damping, G₂(0)), and random hidden units make them
    vary by some ten percent over millimetres."""

    def __init__(self, d, m, hidden=12, seed=0):
        super().__init__(d, m)
        self.shape = FingerShape(d, m)
        rng = np.random.default_rng(seed)
        k, n_out = 2 * d, 2 * d * d + d * m
        A0, G0 = ShapedModel(d, m).AG(np.zeros((1, k)))
        rest = np.concatenate([A0[0, d:, :].ravel(), G0[0, d:, :].ravel()])
        w1 = rng.normal(0, 1.0, (k, hidden)) * np.r_[np.full(d, 300.0), np.full(d, 3.0)][:, None]
        b1 = rng.normal(0, 0.5, hidden)
        w2 = rng.normal(0, 0.3, (hidden, hidden))
        b2 = rng.normal(0, 0.3, hidden)
        w3 = rng.normal(0, 0.05, (hidden, n_out)) * np.abs(rest)[None, :]
        self._layers = [w1, b1, w2, b2, w3, np.zeros(n_out)]
        self._layers[5] = rest - self._out(np.zeros((1, k)))[0]       # the rest blocks at x = 0

    def _out(self, x):
        w1, b1, w2, b2, w3, b3 = self._layers
        h1 = np.maximum(x @ w1 + b1, 0.0)
        return np.maximum(h1 @ w2 + b2, 0.0) @ w3 + b3

    @property
    def fused_network(self):
        return tuple(np.array(a, dtype=np.float64) for a in self._layers)

    def sdc_blocks(self, x):
        d, m = self.d, self.m
        out = self._out(np.atleast_2d(np.asarray(x, dtype=float)))
        return out[:, :2 * d * d].reshape(-1, d, 2 * d), out[:, 2 * d * d:].reshape(-1, d, m)

    def _AG(self, x):
        d = self.d
        a2, g2 = self.sdc_blocks(x)
        n = len(a2)
        A = np.zeros((n, 2 * d, 2 * d))
        A[:, :d, d:] = np.eye(d)
        A[:, d:, :] = a2
        G = np.zeros((n, 2 * d, self.m))
        G[:, d:, :] = g2
        return A, G


def make_pair(law, model, bounds, n, **options):
    """The law compiled (the general kernels) and in numpy, otherwise the same."""
    cls = SdreLaw if law == 'sdre' else SdreFeedforwardLaw
    return tuple(cls(model, W, U_MAX, n_fingers=n, dt=DT, bounds=bounds, compiled=c, **options)
                 for c in (True, False))


def assert_same_step(a, b, bounds):
    """The compiled step ``a`` is the numpy step ``b`` to rounding, and within the bounds."""
    scale = max(np.abs(b.u_unsat).max(), np.abs(b.u).max(), 1e-12)
    np.testing.assert_allclose(a.u_unsat, b.u_unsat, rtol=0, atol=U_RTOL * scale)
    np.testing.assert_allclose(a.u, b.u, rtol=0, atol=U_RTOL * scale)
    np.testing.assert_allclose(a.K, b.K, rtol=0, atol=1e-6 * max(np.abs(b.K).max(), 1e-12))
    np.testing.assert_array_equal(a.ok, b.ok)
    np.testing.assert_array_equal(a.fallback, b.fallback)
    np.testing.assert_array_equal(a.failed_checks, b.failed_checks)
    np.testing.assert_array_equal(a.saturated, b.saturated)
    np.testing.assert_allclose(a.unreachable, b.unreachable, rtol=1e-7, atol=1e-9)
    assert np.all(np.isfinite(a.u))
    assert np.all(a.u >= bounds.lower) and np.all(a.u <= bounds.upper)


def closed_loop(law_a, law_b, model, bounds, steps=150, noise=2e-5, seed=0):
    """Both laws along the model's closed loop under ``law_a`` (two fingers: one on a reference
    the model can follow, one held off it), every step compared; returns law_a's steps."""
    d = model.d
    pos, vel, acc = model_reference(model, input_signal(bounds, hz=2.0, level=0.15),
                                    seconds=steps * DT, dt=DT)
    rng = np.random.default_rng(seed)
    x = np.zeros((2, 2 * d))
    x[1, :d] = 1e-3
    out = []
    for k in range(steps):
        est = x[:, :d] + REST[:d] + noise * rng.standard_normal((2, d))
        ref_p = np.stack([pos[k], pos[k] + 5e-4])
        ref_v, ref_a = np.stack([vel[k]] * 2), np.stack([acc[k]] * 2)
        a = law_a.compute(est, x[:, d:].copy(), ref_p, ref_v, ref_acc=ref_a)
        b = law_b.compute(est, x[:, d:].copy(), ref_p, ref_v, ref_acc=ref_a)
        assert_same_step(a, b, bounds)
        for i in range(2):
            x[i] = rk4(model, x[i], a.u[i], DT)
        out.append(a)
    return out


@pytest.mark.parametrize('shape', list(CASES), ids=[f'd{d}m{m}' for d, m in CASES])
@pytest.mark.parametrize('law', ['sdre', 'sdre_ff'])
def test_the_general_kernels_are_the_numpy_general_path_along_a_closed_loop(shape, law):
    d, m = shape
    bounds = CASES[shape]
    model = FusedShapedModel(d, m)
    compiled, numpy_law = make_pair(law, model, bounds, 2)
    assert compiled.sdre.general_kernels and compiled.network is not None
    assert not numpy_law.sdre.general_kernels and numpy_law.network is None
    steps = closed_loop(compiled, numpy_law, model, bounds)
    # the kernels solved the warm fingers: scipy on the first step and where numpy needed it
    assert compiled.sdre.exact_solves == numpy_law.sdre.exact_solves
    assert compiled.sdre.exact_solves <= 4
    assert np.mean([s.nk_iterations.mean() for s in steps[1:]]) >= 1.0
    assert all(s.ok.all() for s in steps)
    if law == 'sdre_ff':
        assert compiled.integral is not None and np.any(compiled.integral.xi != 0.0)
        np.testing.assert_allclose(compiled.integral.xi, numpy_law.integral.xi, rtol=1e-6,
                                   atol=1e-12)
        if m < d:                                        # a demand no input reaches, reported
            assert max(s.unreachable.max() for s in steps) > 0.0


@pytest.mark.parametrize('ff_at', ['x', 'ref'])
def test_the_feedforward_at_the_reference_and_without_integral_is_the_numpy_path(ff_at):
    model = FusedShapedModel(3, 2, seed=1)
    bounds = CASES[(3, 2)]
    compiled, numpy_law = make_pair('sdre_ff', model, bounds, 2, ff_at=ff_at, integral_gain=0.0)
    assert compiled.integral is None
    closed_loop(compiled, numpy_law, model, bounds, steps=60)


@pytest.mark.parametrize('shape', [(2, 1), (3, 3), (2, 4)], ids=['d2m1', 'd3m3', 'd2m4'])
def test_a_model_with_ag_only_runs_the_compiled_gains_as_numpy_does(shape):
    """A model without a fused network (ShapedModel): the compiled step on its blocks."""
    d, m = shape
    model = ShapedModel(d, m)
    compiled, numpy_law = make_pair('sdre_ff', model, CASES[shape], 2)
    assert compiled.sdre.general_kernels and compiled.network is None
    closed_loop(compiled, numpy_law, model, CASES[shape], steps=60)
    assert compiled.sdre.exact_solves == 2


@pytest.mark.parametrize('law', ['sdre', 'sdre_ff'])
def test_non_finite_inputs_give_finite_commands_within_the_bounds(law):
    d, m = 3, 3
    bounds = CASES[(d, m)]
    model = FusedShapedModel(d, m)
    compiled, numpy_law = make_pair(law, model, bounds, 3)
    pos = np.tile(REST[:d] + 2e-4, (3, 1))
    vel, ref = np.zeros((3, d)), np.tile(REST[:d], (3, 1))
    acc = np.zeros((3, d))
    for k in range(4):                                       # warm first, then the faults
        p, r, a = pos.copy(), ref.copy(), acc.copy()
        if k >= 2:
            p[0, 1] = np.nan                                 # a lost estimate
            r[1, 2] = np.inf                                 # a broken reference
            a[2, 0] = np.nan                                 # a broken acceleration
        s, t = (law_.compute(p, vel, r, vel, ref_acc=a) for law_ in (compiled, numpy_law))
        assert_same_step(s, t, bounds)
    assert not s.ok[0] and not s.ok[1] and s.fallback[:2].all()
    if law == 'sdre':                       # sdre_ff solves a lost finger at x = x_d = 0
        assert s.failed_checks[0] & Check.NONFINITE
    np.testing.assert_array_equal(s.u[:2], np.clip(0.0, bounds.lower, bounds.upper)[None]
                                  .repeat(2, 0))
    if law == 'sdre_ff':
        assert s.ok[2] and s.fallback[2] and s.unreachable[2] == 0.0


@pytest.mark.parametrize('shape', [(2, 3), (3, 3), (2, 1)], ids=['d2m3', 'd3m3', 'd2m1'])
def test_a_failed_warm_start_is_solved_again_in_the_kernel_to_numpys_step(shape):
    """Anti-stabilising warm starts (a fixed point of Newton's iteration): the kernel's checks
    reject Newton–Kleinman's result, the kernel solves each finger again from scratch (the
    Hamiltonian's sign function, then Newton–Kleinman) without scipy, and the step is numpy's,
    whose supervisor solves them with scipy."""
    d, m = shape
    model = FusedShapedModel(d, m)
    bounds = CASES[shape]
    compiled, numpy_law = make_pair('sdre', model, bounds, 2)
    args = (np.tile(REST[:d] + 1e-4, (2, 1)), np.zeros((2, d)), np.tile(REST[:d], (2, 1)),
            np.zeros((2, d)))
    for law in (compiled, numpy_law):
        law.compute(*args)
        law.sdre.warm_start(-np.tile(np.eye(2 * d), (2, 1, 1)))      # anti-stabilising
    a, b = compiled.compute(*args), numpy_law.compute(*args)
    assert_same_step(a, b, bounds)
    assert a.ok.all() and not a.failed_checks.any()
    assert compiled.sdre.exact_solves == 2 and numpy_law.sdre.exact_solves == 4  # the cold step's
    assert np.all(a.nk_iterations >= 1)


def test_a_finger_the_restart_cannot_solve_goes_to_scipy_as_numpy_does():
    """With a residual tolerance nothing meets, Newton–Kleinman and the solve from scratch both
    fail: the finger ends cold, scipy solves it (and fails the same check), and the step, the
    gains kept, is numpy's."""
    model = FusedShapedModel(2, 3)
    bounds = CASES[(2, 3)]
    compiled, numpy_law = make_pair('sdre', model, bounds, 2)
    args = (np.tile(REST[:2] + 1e-4, (2, 1)), np.zeros((2, 2)), np.tile(REST[:2], (2, 1)),
            np.zeros((2, 2)))
    for law in (compiled, numpy_law):
        law.compute(*args)
        law.sdre.warm_start(-np.tile(np.eye(4), (2, 1, 1)))
        sdre = law.sdre                    # the tolerance of both paths, after the cold step
        sdre.residual_tol = 0.0
        sdre._general_settings = (*sdre._general_settings[:3], 0.0, *sdre._general_settings[4:])
    a, b = compiled.compute(*args), numpy_law.compute(*args)
    assert_same_step(a, b, bounds)
    assert not a.ok.any() and np.all(a.failed_checks & Check.RESIDUAL)
    assert compiled.sdre.exact_solves == 4


def test_the_network_kernel_is_the_models_blocks():
    for (d, m) in INPUT_MAPS:
        model = FusedShapedModel(d, m, seed=d * 10 + m)
        x = np.random.default_rng(0).normal(0, 2e-3, (5, 2 * d))
        a2, g2 = np.empty((5, d, 2 * d)), np.empty((5, d, m))
        kernels.shaped_forward(x, *kernels.SdcNetwork.pack(*model.fused_network), a2, g2)
        A2, G2 = model.sdc_blocks(x)
        np.testing.assert_allclose(a2, A2, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(g2, G2, rtol=1e-12, atol=1e-9)


def test_the_lyapunov_solve_is_scipys():
    from scipy.linalg import solve_continuous_lyapunov
    rng = np.random.default_rng(3)
    for k in (4, 6):
        A = rng.normal(size=(k, k)) - 3 * np.eye(k)
        Q = rng.normal(size=(k, k))
        Q = Q @ Q.T
        nu = k * (k + 1) // 2
        L, p = np.empty((nu, nu)), np.empty(nu)
        general.general_lyapunov_operator(A, L)
        iu = np.triu_indices(k)
        p[:] = -Q[iu]
        assert kernels.linalg.solve_in_place(L, p)
        P = np.zeros((k, k))
        P[iu] = p
        P = P + np.triu(P, 1).T
        np.testing.assert_allclose(P, solve_continuous_lyapunov(A.T, -Q), rtol=1e-10, atol=1e-12)


def test_the_laws_of_every_shape_compile_nothing_after_warm_up():
    kernels.warm_up()
    counts = {k.py_func.__name__: len(k.signatures) for k in kernels.cache.KERNELS}
    for shape in ((2, 1), (3, 3)):
        model = FusedShapedModel(*shape)
        for law in ('sdre', 'sdre_ff'):
            compiled, numpy_law = make_pair(law, model, CASES[shape], 2)
            closed_loop(compiled, numpy_law, model, CASES[shape], steps=3)
        compiled, numpy_law = make_pair('sdre', ShapedModel(*shape), CASES[shape], 2)
        closed_loop(compiled, numpy_law, model, CASES[shape], steps=3)
    assert {k.py_func.__name__: len(k.signatures) for k in kernels.cache.KERNELS} == counts


def test_the_general_kernels_serve_only_the_fast_method_with_detectable_weights():
    model = FusedShapedModel(3, 3)
    ref = SdreLaw(model, W, U_MAX, n_fingers=1, method='reference', bounds=CASES[(3, 3)])
    assert not ref.sdre.general_kernels and ref.network is None
    velocity_only = SdreLaw(model, Weights(0.0, 1.0, 1.0), U_MAX, n_fingers=1,
                            bounds=CASES[(3, 3)])
    assert not velocity_only.sdre.general_kernels          # no detectability argument: numpy


def test_the_general_kernels_check_bits_are_riccatis():
    for name in ('HURWITZ', 'ACL_SINGULAR', 'SOLVE_FAILED', 'NONFINITE', 'RESIDUAL', 'P_NOT_PD'):
        assert getattr(general, name) == int(Check[name])


def test_the_bench_times_the_3d_controller_against_the_numpy_path_in_one_run():
    """tools/benchmarks/bench_compute's (d = 3, m = 3) rows: both paths on the same steps, five
    repeats each, the same torques, the compiled one faster."""
    from soft_gripper_sdre.tools.benchmarks.bench_compute import bench_shaped
    r = bench_shaped(2, repeats=5, steps=40, numpy_every=4)
    assert all(len(r[k]) == 5 for k in ('compiled', 'compiled_paired', 'numpy', 'iterations'))
    assert r['difference'] < 1e-7
    assert np.median(r['numpy']) > 2.0 * np.median(r['compiled_paired'])
    assert 1.0 <= np.median(r['iterations']) <= 5.0


def test_bad_settings_of_the_general_path_are_refused_naming_them():
    model = FusedShapedModel(3, 3)
    with pytest.raises(ValueError, match='compiled must be True or False'):
        SdreLaw(model, W, U_MAX, n_fingers=1, bounds=CASES[(3, 3)], compiled='yes')
    for compiled in (True, False):
        law = SdreFeedforwardLaw(model, W, U_MAX, n_fingers=2, bounds=CASES[(3, 3)],
                                 compiled=compiled)
        args = (np.tile(REST, (2, 1)), np.zeros((2, 3)), np.tile(REST, (2, 1)), np.zeros((2, 3)))
        with pytest.raises(ValueError, match=r'ref_acc must have shape \(2, 3\)'):
            law.compute(*args, ref_acc=np.zeros((2, 2)))
        with pytest.raises(ValueError, match='pos, vel, ref_pos, ref_vel'):
            law.compute(args[0][:, :2], *args[1:])


def test_the_pseudo_inversion_kernel_is_numpys_well_and_ill_conditioned():
    """The closed form (a well conditioned G2), the SVD (conditioned worse, or rank deficient)
    and the refusals (singular, zero, not finite) against laws.feedforward.pseudo_inversion."""
    from soft_gripper_sdre.control.laws.feedforward import pseudo_inversion
    rng = np.random.default_rng(7)
    for d, m in INPUT_MAPS:
        G2 = rng.normal(size=(7, d, m))
        k = min(d, m)
        U, _, Vt = np.linalg.svd(G2[1], full_matrices=False)
        G2[1] = U @ np.diag(np.logspace(0, -6, k)) @ Vt          # cond 1e6: the SVD, usable
        G2[2] = U @ np.diag(np.logspace(0, -12, k)) @ Vt         # cond 1e12: refused
        G2[3] = 0.0
        G2[4, 0, 0] = np.nan
        if k > 1:
            G2[5] = np.outer(G2[5, :, 0], G2[5, 0, :])           # rank one
        A2, xd = rng.normal(size=(7, d, 2 * d)), rng.normal(size=(7, 2 * d))
        ad = rng.normal(size=(7, d))
        u, usable, unreachable = pseudo_inversion(A2, G2, xd, ad)
        for i in range(7):
            ui = np.zeros(m)
            ok, unreach = general.finger_pseudo_inversion(A2[i], G2[i], xd[i], ad[i], 1e8, ui)
            assert ok == usable[i], (d, m, i)
            np.testing.assert_allclose(ui, u[i], rtol=1e-9, atol=1e-9 * np.abs(u[i]).max())
            np.testing.assert_allclose(unreach, unreachable[i], rtol=1e-7, atol=1e-9)
        assert usable[[0, 1, 6]].all() and not usable[[3, 4]].any()
        assert usable[2] == (k == 1)                 # one singular value: nothing to compare
