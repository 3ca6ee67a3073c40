"""The training benchmark (tools/benchmarks/bench_train.py): its rows (the total's median and
min-max, each stage's median and share, the load) from the runs' timings, kept as JSON for
`make bench`; bad arguments refused with exit status 2, no traceback, nothing written."""
import json
import subprocess
import sys

import pytest

from soft_gripper_sdre.tools.benchmarks import bench_train


def _run(total, load, **stages):
    return {'timings': {**stages, 'total': total}, 'load': load, 'wall': total + 1.0, 'fit': True,
            'free_run_mm': 0.5, 'bandwidth_hz': 4.0, 'epochs_run': 100}


RUNS = [_run(60.0, 2.0, labels=1.0, label_stage=10.0, loop_settings=40.0),
        _run(50.0, 4.0, labels=2.0, label_stage=12.0, loop_settings=30.0),
        _run(90.0, 1.0, labels=1.5, label_stage=11.0, loop_settings=70.0)]


def test_a_row_gives_the_median_and_spread_of_the_total_each_stages_share_and_the_load():
    s = bench_train.summary('tendon3', RUNS)
    assert s['total'] == [60.0, 50.0, 90.0] and s['load'] == [2.0, 1.0, 4.0] and s['runs'] == 3
    assert s['stages']['labels'] == {'median': 1.5, 'share': 1.5 / 60.0}
    assert [t['total'] for t in s['timings']] == [60.0, 50.0, 90.0]
    assert s['stages']['loop_settings']['median'] == 40.0
    assert list(s['stages']) == ['labels', 'label_stage', 'loop_settings']   # tool's order
    what, figure, note = bench_train.row_text(s)
    assert what == 'training, tendon3' and figure == '60 s (50–90)'
    assert note.startswith('median (min–max) of 3 runs, load 2.0 (1.0–4.0)')
    assert 'loop settings 40.0 s (67 %)' in note
    assert s['wall'] == [61.0, 51.0, 91.0]
    assert note.endswith('imports included: 61 s (51–91)')
    older = {k: v for k, v in s.items() if k != 'wall'}          # rows kept without the wall
    assert bench_train.row_text(older)[2] == note.split('; the command from start')[0]


def test_the_rows_make_bench_shows_are_the_ones_written(tmp_path):
    path = tmp_path / 'bench_train.json'
    assert bench_train.rows(path) == []
    path.write_text(json.dumps({'cases': [bench_train.summary('a', RUNS),
                                          bench_train.summary('b', RUNS[:1])]}))
    got = bench_train.rows(path)
    assert [r[0] for r in got] == ['training, a', 'training, b'] and got[1][1] == '60 s (60–60)'


@pytest.mark.parametrize('args, message', [
    ([], 'give --hand-data'),
    (['--runs', '0', '--hand-data', '.'], '--runs must be >= 1'),
    (['--bags', 'no-equals-sign'], '--bags takes NAME=DIR'),
    (['--bags', '=x'], '--bags takes NAME=DIR'),
    (['--bags', 'empty={tmp}'], 'needs'),
    (['--hand-data', '{tmp}/missing'], 'is not a directory'),
])
def test_bad_arguments_are_refused_with_status_2_and_nothing_written(tmp_path, args, message):
    args = [a.replace('{tmp}', str(tmp_path)) for a in args]
    out = tmp_path / 'rows.json'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.benchmarks.bench_train',
                           *args, '--write', str(out), '--out', str(tmp_path / 'runs')],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert message in proc.stderr and 'Traceback' not in proc.stderr
    assert not out.exists() and not (tmp_path / 'runs').exists()


def test_the_stages_are_read_off_the_tools_line():
    out = ('training: 3 epochs\nstages [s], 452.7 in all: read 0.1, labels 19.4, training 426.2 '
           '(label_stage 426.2, simulation_stage 0.0), checkpoint 4.1, report 3.1\n')
    assert bench_train.printed_stages(out) == {
        'read': 0.1, 'labels': 19.4, 'training': 426.2, 'label_stage': 426.2,
        'simulation_stage': 0.0, 'checkpoint': 4.1, 'report': 3.1, 'total': 452.7}
    assert bench_train.printed_stages('no such line\n') == {}
