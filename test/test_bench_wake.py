"""The wake-up rows: the loop's own callbacks timed on the shipped defaults, every call answered."""
import pytest

from soft_gripper_sdre.tools.benchmarks import wake

# callbacks timed against each other: alone, after the parallel tests (Makefile)
pytestmark = [pytest.mark.ros, pytest.mark.serial]


def test_every_way_times_answered_calls_and_the_rows_give_each_against_warm():
    costs = wake.wake_costs(repeats=2, calls=30)
    load = costs.pop('load')
    assert len(load.seen) == 2
    for name in ('estimator', 'controller'):
        ways = costs[name]
        assert set(ways) <= set(wake.WAYS) and {'warm', 'sleep', 'busy'} <= set(ways)
        for runs in ways.values():
            assert len(runs) == 2 and all(0 < t < 0.1 for t in runs)
    rows = wake.wake_rows(quick=True)
    assert [r[0].split(': ')[1].split("'")[0] for r in rows] == ['estimator', 'controller']
    for _, value, note in rows:
        assert value.endswith('back to back') and 'after sleeping 0.5 ms' in note
        assert 'after busy-waiting 0.5 ms' in note and '×)' in note and 'load' in note


def test_the_command_refuses_bad_arguments_with_status_2(capsys):
    with pytest.raises(SystemExit) as exc:
        wake.main(['--runs', '3'])
    assert exc.value.code == 2 and 'unrecognized arguments' in capsys.readouterr().err
