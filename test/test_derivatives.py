"""KF + RTS derivative estimates: a closed-form track, real simulator data, jerk-intensity
tuning."""
import numpy as np
import pytest

from soft_gripper_sdre.learning import derivatives
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.learning.collect import collect_signal

DT = 1e-3
NOISE_STD = 5e-6     # 5 µm tip measurement noise


def constant_acceleration_track(n: int = 2000):
    """Noiseless 2-axis track p0 + v0 t + a0 t²/2 with its true velocity and acceleration."""
    t = np.arange(n) * DT
    p0, v0, a0 = np.array([0.01, -0.02]), np.array([0.05, -0.01]), np.array([0.3, -1.2])
    pos = p0 + v0 * t[:, None] + 0.5 * a0 * t[:, None] ** 2
    return t, pos, v0 + a0 * t[:, None], np.broadcast_to(a0, pos.shape)


@pytest.fixture(scope='module')
def noisy_record():
    """1 s of the x1 excitation (independent torques) on the simulated finger, 5 µm noise."""
    return collect_signal('x1', SimConfig(scene='finger', noise_std=NOISE_STD, seed=3),
                          duration=1.0)


def test_noiseless_constant_acceleration_track_is_recovered_after_the_start():
    """Past the first 100 samples the smoothed p, ṗ, p̈ of a constant-acceleration track are
    exact."""
    t, pos, vel, acc = constant_acceleration_track()
    p, v, a = derivatives.estimate_kinematics(t, pos, jerk_psd=1.0, meas_std=0.0)
    assert p.shape == v.shape == a.shape == pos.shape
    late = slice(100, None)
    np.testing.assert_allclose(p[late], pos[late], atol=1e-10)
    np.testing.assert_allclose(v[late], vel[late], atol=1e-8)
    np.testing.assert_allclose(a[late], acc[late], atol=1e-6)


def test_noiseless_constant_acceleration_track_is_recovered_from_the_first_sample():
    """The offline smoother has the whole record, so even the first samples must be exact."""
    t, pos, vel, acc = constant_acceleration_track()
    p, v, a = derivatives.estimate_kinematics(t, pos, jerk_psd=1.0, meas_std=0.0)
    np.testing.assert_allclose(p, pos, atol=1e-9)
    np.testing.assert_allclose(v, vel, atol=1e-6)
    np.testing.assert_allclose(a, acc, atol=1e-4)


def test_rts_acceleration_beats_finite_differences_on_simulator_data(noisy_record):
    """On measured (noisy) tip positions the KF + RTS p̈ is far closer to the true p̈ than Δ²p/Δt²."""
    t, tip = noisy_record['t'], noisy_record['tip'][:, :2]
    acc_true, vel_true = noisy_record['acc_true'][:, :2], noisy_record['vel_true'][:, :2]
    q = derivatives.tune_jerk_psd(t[:500], tip[:500], NOISE_STD)
    _, vel, acc = derivatives.estimate_kinematics(t, tip, q, NOISE_STD)
    err = derivatives.estimate_errors(vel, acc, vel_true, acc_true)
    acc_fd = (tip[2:] - 2 * tip[1:-1] + tip[:-2]) / DT ** 2          # central, at t_1 .. t_{N-2}
    fd_rmse = np.sqrt(np.mean((acc_fd - acc_true[1:-1]) ** 2, axis=0))
    assert np.all(np.array(err['acc_rmse']) < fd_rmse / 10), (err['acc_rmse'], fd_rmse)
    assert min(err['acc_r2']) > 0.9, err
    assert max(err['vel_rmse']) < 5e-3, err


def test_tuned_jerk_psd_maximises_the_likelihood_over_its_neighbours(noisy_record):
    """tune_jerk_psd returns a finite positive grid value whose likelihood beats both neighbours."""
    t, tip = noisy_record['t'][:400], noisy_record['tip'][:400, :2]
    grid = np.logspace(0, 8, 9)
    q = derivatives.tune_jerk_psd(t, tip, NOISE_STD, grid)
    assert np.isfinite(q) and q > 0
    i = int(np.flatnonzero(grid == q)[0])
    assert 0 < i < grid.size - 1, f'q = {q:g} sits on the edge of the grid: no interior maximum'
    best = derivatives.innovation_loglik(t, tip, q, NOISE_STD)
    assert np.isfinite(best)
    for neighbour in (grid[i - 1], grid[i + 1]):
        assert best > derivatives.innovation_loglik(t, tip, neighbour, NOISE_STD)


@pytest.mark.parametrize('change, match', [
    (dict(jerk_psd=0.0), 'jerk_psd'), (dict(jerk_psd=np.nan), 'jerk_psd'),
    (dict(t=np.r_[0.0, 1e-3, 3e-3, 4e-3]), 'uniformly'), (dict(pos=np.zeros((3, 2))), 'N >= 3')])
def test_bad_arguments_are_value_errors(change, match):
    """Invalid q, a non-uniform time grid or mismatched lengths raise ValueError naming the
    problem."""
    args = dict(t=np.arange(4) * DT, pos=np.zeros((4, 2)), jerk_psd=1.0, meas_std=0.0)
    args.update(change)
    with pytest.raises(ValueError, match=match):
        derivatives.estimate_kinematics(**args)


def _synthetic_records(n=600, seed=3):
    """Every signal the identifying data name, as records of a noisy sinusoidal tip (no ground
    truth)."""
    from soft_gripper_sdre.learning.dataset import Record
    from soft_gripper_sdre.learning.labels import DATA_VARIANTS, VALIDATION
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    records = {}
    for k, name in enumerate(list(DATA_VARIANTS['identifying']) + [VALIDATION]):
        tip = np.zeros((n, 3))
        tip[:, 0] = 1e-3 * np.sin((2 + k) * t) + NOISE_STD * rng.standard_normal(n)
        tip[:, 1] = -0.01 + 1e-3 * np.cos((3 + k) * t) + NOISE_STD * rng.standard_normal(n)
        records[name] = Record(name, t, rng.normal(size=(n, 2)) * 0.01, tip,
                               np.array([0.0, -0.01, 0.0]), DT, noise_std=NOISE_STD)
    return records


def _filterpy_smoothed(t, pos, jerk_psd, meas_std):
    """filterpy's own batch_filter and rts_smoother, one filter object per column: (3, N, d)."""
    dt = float(np.median(np.diff(t)))
    out = np.empty((3,) + pos.shape)
    for j in range(pos.shape[1]):
        kf = derivatives._started_filter(pos[0, j], dt, jerk_psd, meas_std)
        means, covs, _, _ = kf.batch_filter(pos[:, j], update_first=True)
        means, _, _, _ = kf.rts_smoother(means, covs)
        out[:, :, j] = means[:, :, 0].T
    return out


def test_the_stacked_smoother_is_filterpys_bit_for_bit(noisy_record):
    """estimate_kinematics runs filterpy's arithmetic on stacks of columns: the same bits as
    filterpy's filter object per column, on the simulator's noisy finger and on random walks of
    other lengths, periods, intensities and column counts; Σ_v is Q_continuous_white_noise's."""
    from filterpy.common import Q_continuous_white_noise
    r = noisy_record
    cases = [(r['t'], r['tip'][:, :2], 1e4, NOISE_STD)]
    rng = np.random.default_rng(5)
    for n, d, dt, q, sigma in ((7, 1, 1e-3, 1.0, 0.0), (300, 3, 2e-3, 3e5, 1e-4),
                               (1000, 2, 1 / 300, 10.0, 5e-6)):
        cases.append((np.arange(n) * dt, 1e-3 * np.cumsum(rng.standard_normal((n, d)), axis=0),
                      q, sigma))
    for t, pos, q, sigma in cases:
        got = np.array(derivatives.estimate_kinematics(t, pos, q, sigma))
        assert np.array_equal(got, _filterpy_smoothed(t, pos, q, sigma)), (pos.shape, q)
        dt = float(np.median(np.diff(t)))
        assert np.array_equal(derivatives._process_noise(dt, q),
                              Q_continuous_white_noise(dim=3, dt=dt, spectral_density=q))


def test_labels_of_signals_smoothed_together_are_each_signals_own():
    """label_records smooths the signals sampled alike as one stack: every signal's labels the
    same bits as its own states(), and a signal of another length labelled beside them."""
    from soft_gripper_sdre.learning.labels import label_records, states, states_of
    records = _synthetic_records()
    data = label_records(records, 'identifying')
    train = [states(records[name], data.jerk_psd) for name in data.train_signals]
    for key in ('x', 'acc'):
        assert np.array_equal(getattr(data, key), np.vstack([s[key] for s in train])), key
    alone = states(records['u4'], data.jerk_psd)
    assert all(np.array_equal(data.val[k], alone[k]) for k in alone)
    assert data.x.shape == (5 * 600, 4)
    short = _synthetic_records(n=200, seed=4)['u1']
    mixed = states_of([records['u1'], short, records['u2']], data.jerk_psd)
    for got, record in zip(mixed, (records['u1'], short, records['u2'])):
        own = states(record, data.jerk_psd)
        assert all(np.array_equal(got[k], own[k]) for k in own)
    uneven = _synthetic_records(seed=5)['u2']
    uneven.t[300:] += 0.5 * DT                       # one late sample on: refused, not stacked
    with pytest.raises(ValueError, match='t must be uniformly sampled'):
        states_of([records['u1'], uneven], data.jerk_psd)
