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


def test_labels_in_worker_processes_are_those_labelled_here():
    """label_records' signals labelled side by side in forked workers: every array the same bits
    as one signal after another in this process."""
    from soft_gripper_sdre.learning.labels import label_records
    records = _synthetic_records()
    here = label_records(records, 'identifying', progress=False, workers=1)
    forked = label_records(records, 'identifying', progress=False, workers=2)
    for name in ('x', 'u', 'acc', 'acc_true'):
        assert np.array_equal(getattr(here, name), getattr(forked, name)), name
    assert set(here.val) == set(forked.val)
    assert all(np.array_equal(here.val[k], forked.val[k]) for k in here.val)
    assert here.jerk_psd == forked.jerk_psd and here.x.shape == (5 * 600, 4)


@pytest.mark.parametrize('workers', [0, -1, 1.5, True])
def test_label_workers_must_be_a_positive_int(workers):
    from soft_gripper_sdre.learning.labels import label_records
    with pytest.raises(ValueError, match='workers must be an int >= 1'):
        label_records(_synthetic_records(n=50), 'identifying', progress=False, workers=workers)
