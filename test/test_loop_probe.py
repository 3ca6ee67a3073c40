"""The loop probe (tools/benchmarks/loop_probe.py) records what it claims in a real process, and
gives each late period of a run the cause its timestamps show; the spread of a benchmark figure
(tools/benchmarks/spread.py)."""
import subprocess
import sys

import numpy as np
import pytest

from soft_gripper_sdre.tools.benchmarks.loop_probe import (
    TOPICS,
    graph_periods,
    late_causes,
    probe_env,
)
from soft_gripper_sdre.tools.benchmarks.spread import LoadWatch, figure, span

PERIOD = 1e-3
TIPS, TORQUES = TOPICS.index('/tip_positions'), TOPICS.index('/torque_commands')


def test_a_probed_process_saves_its_collections_and_publishes(tmp_path):
    code = ('import gc, sys\n'
            'import rclpy\n'
            'from rclpy.node import Node\n'
            'from std_msgs.msg import String\n'
            'for _ in range(3):\n'
            '    a = []; a.append(a); del a; gc.collect()\n'
            'rclpy.init(); node = Node("probe_test")\n'
            'pub = node.create_publisher(String, "/torque_commands", 1)\n'
            'pub.publish(String(data="x"))\n'
            'import time\n'
            'timer = node.create_timer(0.001, lambda: time.sleep(0.002))\n'
            'for _ in range(3): rclpy.spin_once(node, timeout_sec=0.1)\n'
            'node.destroy_node(); rclpy.shutdown()\n')
    env = probe_env({k: v for k, v in __import__('os').environ.items()}, tmp_path)
    subprocess.run([sys.executable, '-c', code], env=env, check=True, timeout=120)
    (saved,) = tmp_path.glob('*.npz')
    rec = np.load(saved)
    assert (rec['gc'][:, 1] > 0).all()
    assert (rec['gc'][:, 2] == 2).sum() >= 3                    # gc.collect() is generation 2
    (pub,) = rec['publishes'][rec['publishes'][:, 0] == TORQUES]
    assert pub[0] == TORQUES and pub[1] <= pub[2] and pub[3] == -1.0   # a typed message
    assert len(rec['timers']) >= 2                                      # the timer's callbacks
    assert (rec['timers'][:, 1] - rec['timers'][:, 0] >= 0.002).all()   # each slept 2 ms


def _save_run(where, late_at: dict[int, str], n: int = 50) -> None:
    """A made-up probed run: tick k sends at k ms; the command of k comes back 0.3 ms later,
    except for the ticks of ``late_at`` (the period before is late), whose message is held up by
    the named cause."""
    sent = np.arange(n) * PERIOD + 10.0
    enter, done = sent + 100e-6, sent + 250e-6
    received = sent + 300e-6
    gcs, writes, timers = [], [], []
    for k, cause in late_at.items():
        j = k - 1
        if cause in ('in', 'recorder', 'timer'):        # the callback entered late
            enter[j] += 0.8e-3
            done[j] += 0.8e-3
        if cause == 'recorder':
            writes.append((sent[j] + 50e-6, 0.7e-3))
        if cause == 'timer':                             # /diagnostics ran in the loop process
            timers.append((sent[j] + 50e-6, sent[j] + 750e-6))
        if cause == 'gc':
            gcs.append((sent[j] + 120e-6, 1.0e-3, 0))
        if cause in ('work', 'gc'):
            done[j] += 1.0e-3
        if cause == 'back':
            received[j] += 1.2e-3
        else:
            received[j] = done[j] + 50e-6
    newest = np.array([(received < s).nonzero()[0].max(initial=-1) for s in sent])
    late = newest < np.arange(n) - 1
    stamps = np.arange(n) * PERIOD * 1e9
    np.savez(where / 'ticks.npz', sent=sent, late=late, wake=np.zeros(n), received=received,
             first=5, period=PERIOD)
    cbs = np.stack([np.full(n, TIPS), enter, done, stamps], axis=1)
    pubs = np.stack([np.full(n, TORQUES), done - 20e-6, done, stamps], axis=1)
    np.savez(where / 'controller-1.npz', gc=np.array(gcs).reshape(-1, 3), callbacks=cbs,
             publishes=pubs, writes=np.zeros((0, 2)), timers=np.array(timers).reshape(-1, 2))
    np.savez(where / 'recorder-2.npz', gc=np.zeros((0, 3)), callbacks=np.zeros((0, 4)),
             publishes=np.zeros((0, 4)), writes=np.array(writes).reshape(-1, 2))


@pytest.mark.parametrize('cause', ['in', 'work', 'back', 'gc', 'recorder', 'timer'])
def test_each_late_period_gets_the_cause_its_timestamps_show(tmp_path, cause):
    _save_run(tmp_path, {20: cause, 35: cause})
    out = late_causes(tmp_path)
    assert out['late'] == 2 and out['cause'] == {cause: 2}, out
    assert [d[0] for d in out['detail']] == [20, 35]
    assert out['median_us'] == {'in': 100, 'work': 150, 'back': 50}


def test_periods_on_time_have_no_cause(tmp_path):
    _save_run(tmp_path, {})
    out = late_causes(tmp_path)
    assert out['late'] == 0 and out['cause'] == {} and out['writes'] is None


def test_a_figure_is_the_median_with_the_min_and_max():
    assert figure([3e-6, 1e-6, 2e-6, 5e-6, 4e-6]) == '3 µs (1–5)'
    assert figure([0.5, 0.7, 0.6], '× real time', 1, 2, sep='') == '0.60× real time (0.50–0.70)'
    assert figure([2.0], 's', 1, 1) == '2.0 s' and figure([]) == 'not measured'
    assert span([0.012, 0.031], 100, 1) == '1.2–3.1'
    watch = LoadWatch([0.4, 2.0, 1.3])
    assert watch.text() == 'load 0.4 → 1.3' and LoadWatch().text() == 'load not noted'


def test_a_graph_period_splits_into_its_hops_and_nodes(tmp_path):
    n = 100
    stamps = np.arange(n) * PERIOD * 1e9
    t0 = 5.0 + np.arange(n) * 1.2e-3                 # tips out every 1.2 ms
    marks = [t0 + d for d in (0.0, 120e-6, 270e-6, 320e-6, 520e-6, 560e-6)]
    marks[4][50] += 0.6e-3                           # one controller step 0.6 ms longer
    marks[5][50] += 0.6e-3
    est = TOPICS.index('/state_estimate')

    def rows(topic, start, end):
        return np.stack([np.full(n, topic), start, end, stamps], axis=1)
    empty = {'gc': np.zeros((0, 3)), 'writes': np.zeros((0, 2))}
    np.savez(tmp_path / 'simulator-1.npz', publishes=rows(TIPS, marks[0], marks[0] + 10e-6),
             callbacks=rows(TORQUES, marks[5], marks[5] + 5e-6), **empty)
    np.savez(tmp_path / 'estimator-2.npz', callbacks=rows(TIPS, marks[1], marks[2]),
             publishes=rows(est, marks[2] - 30e-6, marks[2]), **empty)
    np.savez(tmp_path / 'controller-3.npz', callbacks=rows(est, marks[3], marks[4]),
             publishes=rows(TORQUES, marks[4] - 30e-6, marks[4]),
             gc=np.array([[marks[3][50], 0.5e-3, 0]]), writes=np.zeros((0, 2)))
    out = graph_periods(tmp_path)
    assert out['hop tips'][0] == 120 and out['estimator'][0] == 150
    assert out['hop estimate'][0] == 50 and out['controller'][0] == 200
    assert out['hop command'][0] == 40 and out['simulator'][0] == 640
    assert out['period'][0] == 1200
    assert out['round trips longer than a period'] == 1
    assert out['their parts']['controller'] == 800
    assert out['gc']['controller'] == (1, 0.5, 0.5) and out['gc']['estimator'] == (0, 0.0, 0.0)
