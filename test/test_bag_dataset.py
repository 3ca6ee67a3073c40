"""Training data from rosbag2 recordings: every bad bag refused by name, and jittery, gappy,
differently stamped recordings labelled right (real bags written with rosbags, real KF + RTS)."""
import json
import math
import subprocess
import sys

from bag_writing import MS, excitation_bag, tips_messages, torque_messages, write_bag
import numpy as np
import pytest

from soft_gripper_sdre.analysis.bag_dataset import (
    hold_commands,
    label_finger,
    read_recording,
    settle_estimates,
    tip_stretches,
)
from soft_gripper_sdre.analysis.data_facts import DataFacts
from soft_gripper_sdre.analysis.loop_settings import Derivation, LoopSettings
from soft_gripper_sdre.learning.model import read_checkpoint
from soft_gripper_sdre.tools.learning import train as train_tool
from soft_gripper_sdre.tools.learning.train_bags import MAX_DRAWS, RETRY_SCORE, Draw

N = 2000
STAMPS = np.arange(N) * MS
TIPS = np.zeros((N, 1, 3))
TIPS[:, 0, 1] = -0.01 + 1e-3 * np.sin(np.linspace(0, 6, N))
TORQUES = np.full((N, 1, 2), 0.01)


def _bag(tmp_path, tips=None, torques=None, **override):
    topics = {'/tip_positions': tips_messages(STAMPS, TIPS) if tips is None else tips,
              '/torque_commands': torque_messages(STAMPS, TORQUES) if torques is None else torques}
    topics.update(override)
    return write_bag(tmp_path / 'bag', {k: v for k, v in topics.items() if v is not None})


def _nan_tips():
    tips = TIPS.copy()
    tips[700, 0, 0] = np.nan
    return tips_messages(STAMPS, tips)


def _nan_torques():
    u = TORQUES.copy()
    u[5, 0, 1] = np.inf
    return torque_messages(STAMPS, u)


def _reordered():
    msgs = tips_messages(STAMPS, TIPS)
    msgs[300], msgs[301] = ((msgs[300][0], msgs[301][1]),
                            (msgs[301][0], msgs[300][1]))  # bag order kept
    return msgs


def _duplicated():
    stamps = STAMPS.copy()
    stamps[900] = stamps[899]
    return tips_messages(stamps, TIPS)


def _changing_poses():
    msgs = tips_messages(STAMPS, TIPS)
    msgs[50] = (msgs[50][0], tips_messages([STAMPS[50]], np.zeros((1, 2, 3)))[0][1])
    return msgs


BAD_BAGS = {
    'missing tips': (dict(**{'/tip_positions': None}), "no topic 'tip_positions'"),
    'missing torques': (dict(**{'/torque_commands': None}), "no topic 'torque_commands'"),
    'tips of another type': (dict(tips=torque_messages(STAMPS, TORQUES)),
                             'topic /tip_positions has type sensor_msgs/msg/JointState; expected '
                             'geometry_msgs/msg/PoseArray'),
    'torques of another type': (dict(torques=tips_messages(STAMPS, TIPS)),
                                'topic /torque_commands has type geometry_msgs/msg/PoseArray; '
                                'expected sensor_msgs/msg/JointState'),
    'too few messages': (dict(torques=torque_messages(STAMPS[:5], TORQUES[:5])),
                         'topic /torque_commands holds 5 message(s); at least 20 needed'),
    'too short': (dict(torques=torque_messages(STAMPS[:400], TORQUES[:400])),
                  'too short: 400 tips over 0.399 s while commands were given'),
    'reordered stamps': (dict(tips=_reordered()),
                         '/tip_positions stamps do not increase: message 301'),
    'duplicate stamps': (dict(tips=_duplicated()),
                         '/tip_positions stamps do not increase: message 900'),
    'NaN tips': (dict(tips=_nan_tips()),
                 '/tip_positions holds NaN or Inf in 1 message(s), the first stamped 0.700000 s'),
    'Inf torques': (dict(torques=_nan_torques()),
                    '/torque_commands holds NaN or Inf in 1 message(s)'),
    'torques of other joints': (dict(torques=torque_messages(STAMPS, TORQUES,
                                                             names=['left', 'right'])),
                                "names ['left', 'right']; expected '<finger>/ax0' … "
                                "'<finger>/ax<m-1>' for each of the 1"),
    'poses per message change': (dict(tips=_changing_poses()),
                                 '/tip_positions message 50 holds 2 poses, the first held 1'),
    'nothing excited': (dict(torques=torque_messages(STAMPS, np.zeros_like(TORQUES))),
                        'every torque in /torque_commands is zero'),
}


@pytest.mark.parametrize('case', BAD_BAGS)
def test_a_bad_bag_is_refused_naming_the_problem_and_nothing_is_written(case, tmp_path, capsys):
    topics, expected = BAD_BAGS[case]
    bag = _bag(tmp_path, **topics)
    good = excitation_bag(tmp_path / 'good')
    out = tmp_path / 'out'
    for train_bag, val_bag in ((bag, good), (good, bag)):     # as training and as validation data
        with pytest.raises(SystemExit) as exit_info:
            train_tool.main(['--bag', str(train_bag), '--val-bag', str(val_bag), '--out', str(out),
                             '--epochs', '1'])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2, err
        assert f'error: bag {bag}' in err and expected in err, err
        assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ['bag', 'good']


def test_fingers_are_named_by_the_torque_names_in_the_order_they_first_appear(tmp_path):
    tips = np.zeros((N, 2, 3))
    tips[:, 1, 1] = 1e-3                               # pose 1 is the second named finger
    torques = np.stack([np.full((N, 2), 0.01), np.full((N, 2), -0.02)], axis=1)
    msgs = torque_messages(STAMPS, torques,
                           names=['left/ax0', 'left/ax1', 'right/ax0', 'right/ax1'])
    for _, msg in msgs[1:]:  # later messages list the joints in another order
        msg.name = ['right/ax1', 'left/ax0', 'right/ax0', 'left/ax1']
        msg.effort = np.array([-0.02, 0.01, -0.02, 0.01])
    rec = read_recording(write_bag(tmp_path / 'bag', {'/tip_positions': tips_messages(STAMPS, tips),
                                                      '/torque_commands': msgs}))
    assert rec.finger_names == ('left', 'right')
    assert np.all(rec.torques[:, 0] == 0.01) and np.all(rec.torques[:, 1] == -0.02)


def test_a_path_that_is_no_bag_is_refused(tmp_path, capsys):
    good = excitation_bag(tmp_path / 'good')
    with pytest.raises(SystemExit) as exit_info:
        train_tool.main(['--bag', str(tmp_path / 'nothing'), '--val-bag', str(good),
                         '--out', str(tmp_path / 'out')])
    assert exit_info.value.code == 2
    assert f'bag {tmp_path / "nothing"} does not exist' in capsys.readouterr().err


def test_the_cli_exits_2_without_a_traceback(tmp_path):
    """The real process: exit status 2, the message, no traceback, no output directory."""
    bag = _bag(tmp_path, tips=_nan_tips())
    out = tmp_path / 'out'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.learning.train',
                           '--bag', str(bag), '--val-bag', str(bag), '--out', str(out)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert 'holds NaN or Inf' in proc.stderr and 'Traceback' not in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize('args, why', [
    (['--bag', 'a'], '--bag needs --val-bag'),
    (['--val-bag', 'a'], '--bag needs --val-bag'),
    (['--bag', 'a', '--val-bag', 'b', '--data', 'c'], '--data and --bag exclude each other'),
    (['--bag', 'a', '--val-bag', 'b', '--variant', 'paper'],
     '--variant and --jitter apply to --data only'),
    (['--bag', 'a', '--val-bag', 'b', '--meas-std', 'nan'], '--meas-std must be in [0, 0.01) m'),
    (['--bag', 'a', '--val-bag', 'b', '--min-duration', '0'], '--min-duration must be > 0 s'),
    (['--bag', 'a', '--val-bag', 'b', '--finger', '4'], '--finger must be in [0, 3]'),
    (['--bag', 'a', '--val-bag', 'b', '--tries', '0'], '--tries must be in [1, 10]'),
    (['--bag', 'a', '--val-bag', 'b', '--tries', '11'], '--tries must be in [1, 10]'),
    (['--data', 'c', '--tries', '2'], '--tries applies to --bag only'),
    (['--bag', 'a', '--val-bag', 'b', '--rollout-epochs', '-1'],
     '--rollout-epochs takes an int >= 0'),
    (['--data', 'c', '--rollout-epochs', '5'],
     '--rollout-epochs takes an int >= 0 and needs --bag'),
    (['--data', 'c', '--preset', 'gripper'], 'the gripper preset trains on contiguous records'),
    ([], 'give --data DIR'),
])
def test_bad_bag_arguments_are_usage_errors(args, why, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_tool.main(args + ['--out', str(tmp_path / 'out')])
    assert exit_info.value.code == 2 and why in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


# -- irregular recordings -----------------------------------------------------------------------

def _motion(t):
    """A tip motion with known acceleration: position (T, 2) [m] and acceleration (T, 2) [m/s²]."""
    w = np.array([2.0, 3.0]) * np.pi
    pos = np.stack([1e-3 * np.sin(w[0] * t), -0.01 + 2e-3 * np.sin(w[1] * t)], axis=1)
    acc = np.stack([-w[0] ** 2 * 1e-3 * np.sin(w[0] * t), -w[1] ** 2 * 2e-3 * np.sin(w[1] * t)],
                   axis=1)
    return pos, acc


def jittery_bag(path, rng, seconds=4.0, tip_hz=120.0, cmd_hz=250.0, drop=0.01):
    """Tips at ``tip_hz`` with ±20 % stamp jitter and ``drop`` of them lost, commands on stamps of
    their own at ``cmd_hz`` (also jittered), wall-time-like stamps far from 0, two fingers."""
    base = 1_700_000_000 * 10**9
    def stamps(hz):
        k = np.arange(int(seconds * hz))
        return base + np.round((k + rng.uniform(-0.2, 0.2, k.size)) * 1e9 / hz).astype(np.int64)
    tip_ns = stamps(tip_hz)
    tip_ns = tip_ns[rng.random(tip_ns.size) >= drop]
    pos, _ = _motion((tip_ns - base) / 1e9)
    tips = np.zeros((tip_ns.size, 2, 3))
    tips[:, :, :2] = pos[:, None, :]
    cmd_ns = stamps(cmd_hz)
    cmd = np.zeros((cmd_ns.size, 2, 2))
    cmd[:, 1, 0] = np.round(rng.uniform(-0.03, 0.03, cmd_ns.size), 4)     # finger 1 only
    cmd[:, 1, 1] = np.round(rng.uniform(-0.03, 0.03, cmd_ns.size), 4)
    write_bag(path, {'/hand/tip_positions': tips_messages(tip_ns, tips),
                     '/hand/torque_commands': torque_messages(cmd_ns, cmd)})
    return base, tip_ns, cmd_ns, cmd


def test_zero_order_hold_takes_the_last_command_at_or_before_each_time():
    cmd_ns = np.array([10, 20, 35])
    values = np.array([[1.0], [2.0], [3.0]])
    held, age = hold_commands(cmd_ns, values, np.array([5, 10, 19, 20, 34, 35, 99]))
    np.testing.assert_array_equal(held[1:, 0], [1.0, 1.0, 2.0, 2.0, 3.0, 3.0])
    assert np.isnan(held[0, 0]) and age.tolist() == [-1, 0, 9, 0, 14, 0, 64]


def test_jittery_dropped_and_differently_stamped_recording_is_labelled_on_a_uniform_grid(tmp_path):
    rng = np.random.default_rng(3)
    base, tip_ns, cmd_ns, cmd = jittery_bag(tmp_path / 'bag', rng)
    rec = read_recording(tmp_path / 'bag')  # the namespaced topics are found by their last name
    assert rec.n_fingers == 2 and rec.tips_topic == '/hand/tip_positions'
    info = rec.describe()
    assert info['tips']['rate_hz'] == pytest.approx(120.0, rel=0.02) and info['tips']['gaps'] > 0
    assert info['torques']['rate_hz'] == pytest.approx(250.0, rel=0.02)
    assert 0.05 < info['tips']['period_jitter'] < 0.3
    rest, _, _ = settle_estimates(rec, 1)
    [samples] = label_finger(rec, 1, jerk_psd=1e3, meas_std=1e-7, rest_tip=rest)
    assert samples.info['resampled']
    step = np.diff(samples.t)
    assert np.allclose(step, step[0], rtol=1e-6) and step[0] == pytest.approx(1 / 120, rel=0.02)
    # every sample holds the newest command stamped at or before it (brute force), none after the
    # last
    t_ns = tip_ns[0] + np.round(samples.t * 1e9).astype(np.int64)
    for k in range(0, len(t_ns), 7):
        j = np.flatnonzero(cmd_ns <= t_ns[k])[-1]
        np.testing.assert_array_equal(samples.u[k], cmd[j, 1])
    assert t_ns[0] >= cmd_ns[0] and t_ns[-1] < cmd_ns[-1]
    # the labels follow the true acceleration of the motion (away from the ends)
    _, acc_true = _motion((t_ns - base) / 1e9)
    inner = slice(30, -30)
    resid = samples.acc[inner] - acc_true[inner]
    r2 = 1 - (resid ** 2).sum(axis=0) / (
        (acc_true[inner] - acc_true[inner].mean(axis=0)) ** 2).sum(axis=0)
    assert np.all(r2 > 0.98), r2
    np.testing.assert_allclose(samples.x[:, :2] + rest[:2], _motion((t_ns - base) / 1e9)[0],
                               atol=2e-5)


def test_a_long_gap_splits_the_recording(tmp_path):
    stamps = np.concatenate([np.arange(1000), 1500 + np.arange(1000)]) * MS
    tips = np.zeros((2000, 1, 3))
    tips[:, 0, 0] = np.sin(stamps / 1e9)
    write_bag(tmp_path / 'bag', {'/tip_positions': tips_messages(stamps, tips),
                                 '/torque_commands': torque_messages(stamps,
                                                                     np.full((2000, 1, 2), 0.01))})
    rec = read_recording(tmp_path / 'bag')
    assert tip_stretches(rec) == [slice(0, 1000), slice(1000, 2000)]
    parts = label_finger(rec, 0, 1e3, 1e-7, np.zeros(3))
    # the first stretch holds commands up to its end; the second ends before the last command
    assert [len(p.t) for p in parts] == [1000, 999]


def test_training_on_a_jittery_bag_records_the_provenance(tmp_path, capsys):
    rng = np.random.default_rng(5)
    jittery_bag(tmp_path / 'train', rng)
    jittery_bag(tmp_path / 'val', rng, seconds=2.0)
    out = tmp_path / 'out'
    status = train_tool.main(['--bag', str(tmp_path / 'train'), '--val-bag',
                              str(tmp_path / 'val'), '--out', str(out), '--epochs', '2',
                              '--rollout-epochs', '2', '--meas-std', '1e-6'])
    # two epochs make no model fit to control: written and judged, no params.yaml, status 3
    assert status == train_tool.NOT_FIT
    assert 'THE MODEL IS NOT FIT TO CONTROL' in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ['fig2_loss.png', 'fig3_accel_val.png',
                                                     'metrics.json', 'model.pt']
    assert not [p for p in tmp_path.iterdir()
                if p.name.startswith('.out')], 'the staging directory is left'
    data = read_checkpoint(out / 'model.pt')['data']
    [bag] = data['bags']
    assert (bag['path'] == str((tmp_path / 'train').resolve())
            and list(bag['fingers']) == ['finger_1'])
    assert (bag['tips']['topic'] == '/hand/tip_positions'
            and bag['torques']['type'] == 'sensor_msgs/msg/JointState')
    assert (bag['tips']['rate_hz'] == pytest.approx(120.0, rel=0.02)
            and bag['tips']['duration_s'] > 3.5)
    assert bag['fingers']['finger_1']['stretches'][0]['resampled'] is True
    assert (data['noise_std'] == 1e-6
            and data['train_samples'] == bag['fingers']['finger_1']['samples'])
    timings = json.loads((out / 'metrics.json').read_text())['timings']
    assert list(timings) == ['read', 'labels', 'training', 'label_stage', 'simulation_stage',
                             'checkpoint', 'fitness', 'total']     # the model is not fit: no checks
    assert all(v >= 0 for v in timings.values())
    # each stage is kept to 1 ms: their sums may pass the whole by that rounding
    assert timings['label_stage'] + timings['simulation_stage'] <= timings['training'] + 1e-3
    stages = [v for k, v in timings.items()
              if k not in ('label_stage', 'simulation_stage', 'total')]
    assert sum(stages) <= timings['total'] + 1e-3 * len(stages)


def test_the_labels_filter_is_tuned_on_the_excited_tips_not_on_the_rest_before_them(tmp_path):
    """A driver idle for longer than the tuning window, a settle phase, then a fast motion: the
    window starts at the first non-zero torque, and picks the motion's intensity, not the rest's."""
    from soft_gripper_sdre.learning import derivatives
    from soft_gripper_sdre.tools.learning.train_bags import (
        JERK_GRID,
        TUNE_SAMPLES,
        tune_jerk,
        tuning_stretch,
    )
    rng = np.random.default_rng(7)
    stamps = np.arange(4400) * 5 * MS                      # 200 Hz, 22 s
    t = stamps / 1e9
    moving = t >= 12.0
    tips = np.zeros((len(t), 1, 3))
    tips[moving, 0, 0] = 2e-3 * np.sin(2 * np.pi * 6.0 * (t[moving] - 12.0))
    tips[:, 0, :2] += rng.normal(0.0, 5e-5, (len(t), 2))
    cmd_at = t >= 11.0                                     # commands from 11 s: zero until 12 s
    torques = np.zeros((int(cmd_at.sum()), 1, 2))
    torques[t[cmd_at] >= 12.0] = 0.01
    write_bag(tmp_path / 'bag', {'/tip_positions': tips_messages(stamps, tips),
                                 '/torque_commands': torque_messages(stamps[cmd_at], torques)})
    rec = read_recording(tmp_path / 'bag')
    tt, xy = tuning_stretch(rec, 0)
    assert len(tt) == min(TUNE_SAMPLES, int(moving.sum())) and tt[0] == 0.0
    np.testing.assert_array_equal(xy, tips[moving, 0, :2][:len(tt)])
    at_rest = derivatives.tune_jerk_psd(t[:TUNE_SAMPLES], tips[:TUNE_SAMPLES, 0, :2], 5e-5,
                                        JERK_GRID)
    q = tune_jerk(rec, 0, 5e-5)
    assert q >= 100 * at_rest, (q, at_rest)


def _derivation(on_fingers: dict | None, settings: bool = True, score: float = 0.04):
    """A derivation as training gives it: chosen settings (or none), their score on the model and
    what the fingers' own fits expect of them, error / travel by finger."""
    facts = DataFacts(period=0.005, noise_std=5e-5, travel=3e-3, torque_limit=0.01,
                      accel_psd_ml=0.1)
    chosen = LoopSettings(control_period=0.005, meas_std=5e-5, accel_psd=0.1, q_pos=1e3,
                          q_vel=0.0, r=1e4, torque_limit=0.01, torque_lowpass_hz=20.0,
                          integral_gain=1e3, integral_band=3e-3, pd_kp=40.0, pd_kd=9.0,
                          bandwidth_hz=2.0)
    runs = None if on_fingers is None else {
        name: {'rmse_rel': e, 'diverged': e == math.inf} for name, e in on_fingers.items()}
    return Derivation(chosen if settings else None, {}, [], facts, on_fingers=runs,
                      score=score if settings else None)


def test_another_draw_while_the_fits_expect_a_miss_and_the_best_is_kept():
    """The draws' rule (train_bags.Draw): an unfit model, a fit one that gave no setting, one
    whose fingers' fits expect a miss beyond KEEP_NOMINAL, or, without such fits, whose settings
    score over RETRY_SCORE on the model, asks for another seed; the best sorts first: fit, with
    settings, the smaller expected miss, the smaller score, the earlier seed."""
    miss, hit = Draw(0, _derivation({'index': 0.072, 'thumb': 0.029})), \
        Draw(1, _derivation({'index': 0.032, 'thumb': 0.016}))
    assert miss.expected == 0.072 and miss.retry
    assert hit.expected == 0.032 and not hit.retry
    diverges = Draw(2, _derivation({'index': 0.01, 'thumb': math.inf}))
    assert diverges.expected == math.inf and diverges.retry
    nothing = Draw(3, _derivation(None, settings=False))
    assert nothing.expected is None and nothing.retry
    unfit, no_fits = Draw(4, None), Draw(5, _derivation(None))
    assert unfit.retry and not no_fits.retry and no_fits.expected is None
    # no fit expects anything: the score decides, at RETRY_SCORE itself no retry
    at = Draw(6, _derivation(None, score=RETRY_SCORE))
    over = Draw(7, _derivation(None, score=RETRY_SCORE * 1.2))
    assert not at.retry and over.retry and over.score == RETRY_SCORE * 1.2
    # the fits' expectation rules where there is one, whatever the score
    assert not Draw(8, _derivation({'index': 0.03}, score=0.3)).retry
    ranked = sorted([unfit, nothing, over, diverges, miss, at, hit, no_fits], key=Draw.rank)
    assert [d.seed for d in ranked] == [1, 0, 2, 5, 6, 7, 3, 4]
    assert 'index 7.20 %, thumb 2.90 %' in miss.text() and unfit.text() == 'not fit to control'
    assert Draw(9, None, ('the learned rest is unstable', 'a free run diverged')).text() == (
        'not fit to control (the learned rest is unstable; a free run diverged)')
    assert 'score 4.00 %' in miss.text() and 'score' not in nothing.text()
    assert miss.summary() == {'seed': 0, 'fit_for_control': True, 'settings': True,
                              'expected_rmse_rel': 0.072, 'score': 0.04}
    # the tool's help states the rule with the module's numbers
    usage = ' '.join(train_tool._parser().format_help().split())
    assert f'score over {100 * RETRY_SCORE:g} % on the model' in usage
    assert f'(default {MAX_DRAWS}; 1: one training)' in usage
