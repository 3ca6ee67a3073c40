"""Training at its floor: the compiled labels against filterpy's (the same maths to rounding), the
settings that make the bag path's training cheaper (checked when made, and doing what they say),
the stage timings (real KF + RTS, real torch training)."""
from dataclasses import replace
import time

import numpy as np
import pytest

from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.learning.rollout import Run
from soft_gripper_sdre.learning.train_settings import PRESETS, TrainSettings
from soft_gripper_sdre.learning.training import train
from soft_gripper_sdre.sim.shape import FingerShape

GRID = np.logspace(-3, 7, 11)     # the bag path's jerk grid (tools.learning.train_bags)
SIGMA = 5e-5


def _record(n: int = 3000, dt: float = 0.005, seed: int = 0, jitter: float = 0.0):
    """Two noisy tip coordinates [m] of a finger moving at 1.3 and 3.1 Hz, on stamps evenly
    spaced (jitter 0) or jittered by that share of the period."""
    rng = np.random.default_rng(seed)
    steps = dt * np.clip(1.0 + jitter * rng.standard_normal(n - 1), 0.3, None)
    t = np.concatenate([[0.0], np.cumsum(steps)])
    pos = np.stack([0.01 * np.sin(2 * np.pi * 1.3 * t), 0.005 * np.sin(2 * np.pi * 3.1 * t + 1)],
                   axis=1)
    return t, pos + SIGMA * rng.standard_normal(pos.shape)


def _close(compiled, reference):
    """Each of pos, vel, acc agrees with filterpy's: positions to 1e-10 of their range (rounding:
    1e-13 to 2e-12 by the CPU), the derivatives (the smoother subtracts nearly equal covariances)
    to 1e-9."""
    for name, a, b, tol in zip(('pos', 'vel', 'acc'), compiled, reference, (1e-10, 1e-9, 1e-9)):
        assert a.shape == b.shape
        err = float(np.max(np.abs(a - b)) / np.max(np.abs(b)))
        assert err <= tol, f'{name}: {err:.2e} of its range'


@pytest.mark.parametrize('q', [1e-1, 1e2, 1e5])
def test_the_compiled_smoother_is_filterpys_on_even_stamps(q):
    t, pos = _record()
    _close(derivatives.estimate_kinematics(t, pos, q, SIGMA, compiled=True),
           derivatives.estimate_kinematics(t, pos, q, SIGMA))


@pytest.mark.parametrize('q', [1e-1, 1e2, 1e5])
def test_the_compiled_smoother_is_filterpys_on_jittered_stamps_and_a_grid(q):
    t, pos = _record(jitter=0.2)
    dt = 0.005
    grid = np.arange(int(t[-1] // dt) + 1) * dt
    _close(derivatives.estimate_kinematics_irregular(t, pos, grid, q, SIGMA, compiled=True),
           derivatives.estimate_kinematics_irregular(t, pos, grid, q, SIGMA))


@pytest.mark.parametrize('jitter', [0.0, 0.2])
def test_the_compiled_likelihood_is_filterpys_and_tunes_the_same_intensity(jitter):
    """The innovation log-likelihood to 1e-12 at every intensity of the grid, so the same one is
    picked, and the compiled tuning at least 20 times faster, measured in this run."""
    t, pos = _record(n=400, jitter=jitter)
    grid = GRID[::2]
    loglik = (derivatives.innovation_loglik if jitter == 0 else
              derivatives.innovation_loglik_irregular)
    tune = derivatives.tune_jerk_psd if jitter == 0 else derivatives.tune_jerk_psd_irregular
    for q in grid:
        ref = loglik(t, pos, q, SIGMA)
        assert loglik(t, pos, q, SIGMA, compiled=True) == pytest.approx(ref, rel=1e-12, abs=1e-9)
    tune(t, pos, SIGMA, grid, compiled=True)                      # compiled or loaded
    start = time.perf_counter()
    fast = tune(t, pos, SIGMA, grid, compiled=True)
    middle = time.perf_counter()
    slow = tune(t, pos, SIGMA, grid)
    end = time.perf_counter()
    assert fast == slow
    assert (end - middle) > 20 * (middle - start)


def test_the_compiled_smoother_takes_a_one_column_record_and_floors_sigma():
    t, pos = _record(n=200)
    _close(derivatives.estimate_kinematics(t, pos[:, 0], 1e3, 0.0, compiled=True),
           derivatives.estimate_kinematics(t, pos[:, 0], 1e3, 0.0))


@pytest.mark.parametrize('field, value', [('score_every', 0), ('score_every', 1.5),
                                          ('score_every', True), ('rollout_batch_size', 0),
                                          ('rollout_batch_size', 2.0), ('batch_size', 0)])
def test_bad_speed_settings_are_refused_naming_them(field, value):
    with pytest.raises(ValueError, match=field):
        TrainSettings(**{field: value})


def test_the_presets_keep_their_arithmetic_where_the_bits_must_stay():
    """The default preset (the shipped model) scores every epoch, and its simulation-stage batch
    is its label batch: the fields that make training cheaper are at their neutral values."""
    for name in ('default', 'paper'):
        assert PRESETS[name].score_every == 1 and PRESETS[name].rollout_batch_size is None


def _finger_data(n: int = 1200, dt: float = 0.01, seed: int = 3):
    """States, inputs and accelerations of a damped linear finger (d = 2, m = 2) driven by
    random steps, with its contiguous records."""
    rng = np.random.default_rng(seed)
    A = np.array([[-40.0, 0.0, -4.0, 0.0], [0.0, -60.0, 0.0, -5.0]])
    G = np.array([[30.0, 5.0], [-4.0, 25.0]])
    x, xs, us, accs = np.zeros(4), [], [], []
    u = np.zeros(2)
    for k in range(n):
        if k % 25 == 0:
            u = rng.uniform(-0.01, 0.01, 2)
        acc = A @ x + G @ u
        xs.append(x.copy())
        us.append(u.copy())
        accs.append(acc)
        x = x + dt * np.concatenate([x[2:] + dt * acc, acc])
    return np.array(xs), np.array(us), np.array(accs), dt


def test_score_every_scores_only_those_label_epochs_and_the_last_and_keeps_a_scored_one():
    x, u, acc, dt = _finger_data()
    half = len(x) // 2
    runs, val_runs = [Run(x[:half], u[:half], dt)], [Run(x[half:], u[half:], dt)]
    settings = replace(PRESETS['gripper'], epochs=7, rollout_epochs=2, score_every=3,
                       rollout_val_seconds=0.5, rollout_batch_size=64)
    result = train(x[:half], u[:half], acc[:half], x[half:], u[half:], acc[half:], settings,
                   runs=runs, val_runs=val_runs, shape=FingerShape(2, 2))
    assert result.scored_epochs == [0, 3, 6, 7, 8]    # the first, every third, the last label
    assert len(result.rollout_loss) == 2 and len(result.train_loss) == 7      # epoch; rollouts
    sim = result.val_sim_error
    assert len(sim) == 9 and sim[1] == sim[2] == sim[0] and sim[4] == sim[5] == sim[3]
    assert len(set(sim[i] for i in result.scored_epochs)) == 5    # each scored epoch its own run
    assert result.best_epoch in result.scored_epochs
    assert set(result.timings) == {'label_stage', 'simulation_stage'}
    assert all(v > 0 for v in result.timings.values())
    assert sum(result.timings.values()) == pytest.approx(result.seconds, rel=1e-6)


def test_stages_add_laps_in_order_and_print_training_with_its_own_stages():
    from soft_gripper_sdre.analysis.training_run import Stages
    clock = Stages()
    clock.lap('labels')
    time.sleep(0.01)
    clock.lap('checkpoint')
    first = clock.seconds['checkpoint']
    clock.lap('checkpoint')                             # a second lap adds to the first
    clock.seconds.update(training=2.0, label_stage=0.5, simulation_stage=1.5)
    rec = clock.record()
    assert list(rec) == ['labels', 'training', 'label_stage', 'simulation_stage', 'checkpoint',
                         'total']
    assert first >= 0.01 and rec['checkpoint'] >= round(first, 3)
    assert rec['total'] >= rec['labels'] + rec['checkpoint']
    assert 'training 2.0 (label_stage 0.5, simulation_stage 1.5), checkpoint' in clock.line()


def _scored_net(shape, seed: int = 0, gain: float = 1.0):
    """Seeded networks of ``shape`` (their weights times ``gain``), the data's scales, and
    validation windows of a random record."""
    import torch

    from soft_gripper_sdre.learning.model import SDCNet
    from soft_gripper_sdre.learning.rollout import Scales, windows
    torch.manual_seed(seed)
    net = SDCNet(shape=shape)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(gain)
    rng = np.random.default_rng(seed)
    n, dt = 600, 0.005
    x = np.cumsum(rng.normal(0, 1e-4, (n, shape.n_state)), axis=0)
    u = np.repeat(rng.uniform(-0.1, 0.1, (n // 30, shape.m)), 30, axis=0)
    s = Scales(*(torch.as_tensor(a.std(axis=0), dtype=torch.float32) for a in (x, u, x[:, :2])))
    return net, s, windows([Run(x, u, dt)], 0.5, 1)


@pytest.mark.parametrize('shape', [FingerShape(2, 2), FingerShape(3, 3), FingerShape(2, 1)])
def test_the_numpy_score_is_the_torch_runs_to_float32_rounding(shape):
    """The validation free runs scored with the fused float64 network in numpy
    (rollout.val_sim_error) against the torch runs the simulation stage trains on
    (rollout.window_errors), window by window; a diverging network counts the cap in both."""
    import torch

    from soft_gripper_sdre.learning import rollout
    from soft_gripper_sdre.learning.rollout import Scales
    net, s, val = _scored_net(shape)
    s = Scales(s.x, s.u, torch.ones(shape.d) * s.x[:shape.d].mean())
    layers = rollout.fused_network(net, s)
    for dt, x0, u, p in val:
        with torch.no_grad():
            ref = rollout.window_errors(net, s, dt, x0, u, p).double().numpy()
        got = rollout.window_errors_numpy(layers, shape.d, s, dt, x0, u, p)
        assert got.shape == ref.shape and np.all(got > 0)
        assert np.all(ref < rollout.SIM_ERROR_CAP)               # runs that stayed, not caps
        np.testing.assert_allclose(got, ref, rtol=2e-4)
    with torch.no_grad():
        ref = float(np.mean(np.concatenate([rollout.window_errors(net, s, *w).numpy()
                                            for w in val])))
    assert rollout.val_sim_error(net, s, val) == pytest.approx(ref, rel=2e-4)
    wild, _, _ = _scored_net(shape, gain=40.0)               # runs that leave the bound
    assert rollout.val_sim_error(wild, s, val) == pytest.approx(rollout.SIM_ERROR_CAP)


@pytest.mark.parametrize('shape', [FingerShape(2, 2), FingerShape(3, 3), FingerShape(2, 1)])
def test_the_compiled_free_runs_are_numpys_to_rounding(shape):
    """rollout.simulate_compiled (compiled_rollout.free_runs) against simulate_numpy: the same
    positions to 1e-12 for runs that stay, the same bound-held states for runs that leave it, NaN
    where a start is NaN; and the scores val_sim_error takes from them."""
    import torch

    from soft_gripper_sdre.learning import rollout
    from soft_gripper_sdre.learning.rollout import Scales
    net, s, val = _scored_net(shape)
    s = Scales(s.x, s.u, torch.ones(shape.d) * s.x[:shape.d].mean())
    wild, _, _ = _scored_net(shape, gain=40.0)
    for model in (net, wild):
        layers = rollout.fused_network(model, s)
        for dt, x0, u, p in val:
            x0 = x0.clone()
            x0[1] = float('nan')
            ref = rollout.simulate_numpy(layers, shape.d, s, x0, u, dt)
            got = rollout.simulate_compiled(layers, shape.d, s, x0, u, dt)
            assert got.shape == ref.shape
            assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.isnan(got[1]).all()
            np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
            kept = np.isfinite(ref).all(axis=(1, 2))
            errs = [rollout.window_errors_numpy(layers, shape.d, s, dt, x0, u, p, compiled=c)
                    for c in (False, True)]
            np.testing.assert_allclose(errs[1], errs[0], rtol=1e-12)
            assert (errs[1][~kept] == rollout.SIM_ERROR_CAP).all()
    bound = rollout.SIM_BOUND * s.x.double().numpy()
    held = rollout.simulate_compiled(rollout.fused_network(wild, s), shape.d, s, val[0][1],
                                     val[0][2], val[0][0])
    assert np.isclose(np.abs(held), bound[:shape.d]).any()      # the wild runs met the bound
