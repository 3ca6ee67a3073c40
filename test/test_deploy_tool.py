"""tools.graph.deploy: one command from params.yaml to a scored run. Bad arguments and parameter
files exit 2 naming what is wrong, nothing written; the score's bad inputs are refused (no ROS);
and the deployment over DDS against plant_driver (slow): the loop, the plan and the recorder
started, the run ended with the plan, the score printed and kept."""
import json
import os
from pathlib import Path
import subprocess
import sys

from deploy_params import MODEL, NAMES, params_file
import numpy as np
import pytest
import yaml

from soft_gripper_sdre.analysis.run_score import ScoreError, score_run
from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.tools.graph.deploy import loop_report, loop_text
from soft_gripper_sdre.tools.graph.procs import Graph, ros_env

ROOT = Path(__file__).resolve().parents[1]


def _tool(*args, timeout=60, env=None):
    return subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.graph.deploy', *args],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          env=env or {**os.environ, 'PYTHONUNBUFFERED': '1'})


@pytest.mark.parametrize('make, args, message', [
    (None, [], '--params', ),
    ('none', [], 'no such file'),
    ('unfit', [], 'no such file: training judged that model not fit to control (exit status 3)'),
    ('text', [], 'no /**/estimator ros__parameters section'),
    ('ok', ['--law', 'bogus'], "--law: unknown law 'bogus'"),
    ('ok', ['--tail', '-1'], '--tail must be in [0, 600]'),
    ('ok', ['--startup-timeout', 'nan'], '--startup-timeout must be in [1, 3600]'),
    ('ok', ['--domain-id', '500'], '--domain-id must be in [0, 232]'),
    ('no_times', [], 'the trajectory section has no t_hold, t_open'),
    ('bad_time', [], 't_start, t_close, t_hold, t_open must be numbers >= 0 s'),
    ('no_names', [], 'finger_names must be a list of 1 to 4 names'),
    ('no_travel', [], 'close_distance > 0'),
    ('bad_task_dim', [], "the trajectory section's task_dim must be 2 or 3 (the tip's "
                         "coordinates), got 5"),
    ('no_model', [], "the controller's model_path: model file"),
    ('dim_mismatch', [], "the trajectory section's task_dim is 3, the model at model_path has "
                         "2-D tips; give task_dim 2"),
    ('exists', [], 'exists already'),
    ('bad_domain', [], "ROS_DOMAIN_ID 'lab' is not a domain number"),
])
def test_bad_arguments_exit_2_naming_them_with_nothing_written(tmp_path, make, args, message):
    src = tmp_path / 'src'
    src.mkdir()
    path = src / 'params.yaml'
    if make == 'text':
        path.write_text('just: text\n')
    elif make == 'unfit':                  # training's output without its params.yaml
        (src / 'metrics.json').write_text('{}')
    elif make in ('ok', 'exists', 'bad_domain'):
        params_file(path)
    elif make == 'no_times':
        params_file(path, drop=('t_hold', 't_open'))
    elif make == 'bad_time':
        params_file(path, t_start='soon')
    elif make == 'no_names':
        params_file(path, finger_names=[])
        data = yaml.safe_load(path.read_text())
        data['/**/controller']['ros__parameters'].pop('finger_names')
        path.write_text(yaml.safe_dump(data))
    elif make == 'no_travel':
        params_file(path, close_distance=0.0)
    elif make == 'bad_task_dim':
        params_file(path, task_dim=5)
    elif make == 'dim_mismatch':
        params_file(path, task_dim=3)
    elif make == 'no_model':
        params_file(path)
        data = yaml.safe_load(path.read_text())
        data['/**/controller']['ros__parameters']['model_path'] = str(src / 'gone.pt')
        path.write_text(yaml.safe_dump(data))
    out = tmp_path / 'out'
    if make == 'exists':
        out.mkdir()
    before = sorted(p.name for p in src.iterdir())
    env = {**os.environ, 'ROS_DOMAIN_ID': 'lab'} if make == 'bad_domain' else None
    r = _tool(*(['--params', str(path)] if make else []), '--out', str(out), *args, env=env)
    assert r.returncode == 2, r.stderr
    assert message in r.stderr and 'Traceback' not in r.stderr, r.stderr
    assert sorted(p.name for p in src.iterdir()) == before
    assert make == 'exists' or not out.exists()


def test_the_score_refuses_bad_inputs_and_a_bag_without_its_topics(tmp_path):
    b = InputBounds.symmetric(0.02, 2)
    for kwargs, message in ((dict(travel=0.0), 'travel must be finite and > 0 m'),
                            (dict(d=4), 'd must be 2 or 3'),
                            (dict(plan_seconds=float('nan')), 'plan_seconds must be'),
                            (dict(rest_seconds=-1.0), 'rest_seconds must be')):
        args = {**dict(travel=0.01, bounds=b, d=2, plan_seconds=3.0, rest_seconds=0.5), **kwargs}
        with pytest.raises(ScoreError, match=message):
            score_run(tmp_path / 'nobag', **args)
    with pytest.raises(ScoreError, match='nobag does not exist'):
        score_run(tmp_path / 'nobag', 0.01, b, 2, 3.0, 0.5)


def test_the_loop_report_counts_what_happened_while_the_plan_ran():
    start = {'controller': {'estimates': '10', 'skipped_estimates': '2'},
             'recorder': {'lost /tip_positions': '3', 'messages /tip_positions': '40'},
             'lab_driver': {'ticks': '1000', 'late_ticks': '7', 'stale_ticks': '400', 'plant': 'x'}}
    # the trajectory node counts ticks too; the driver is the node that counts late ones
    end = {'trajectory': {'ticks': '9'},
           'controller': {'estimates': '610', 'skipped_estimates': '9', 'estimate_jumps': '1'},
           'estimator': {'estimates': '620', 'resets': '2', 'dropouts': 'n/a'},
           'recorder': {'lost /tip_positions': '5', 'lost /torque_commands': '4'},
           'lab_driver': {'ticks': '1600', 'late_ticks': '27', 'stale_ticks': '400'}}
    report = loop_report(start, end)
    # counted from the plan's start: the driver's stale ticks of an earlier run are not this one's;
    # a value that is not a number counts 0
    assert report == {'controller': {'estimates': 600, 'skipped_estimates': 7, 'estimate_jumps': 1,
                                     'wrong_task_dim': 0},
                      'estimator': {'resets': 2, 'dropouts': 0, 'bad_message': 0},
                      'lost': {'/tip_positions': 2, '/torque_commands': 4},
                      'driver': {'node': 'lab_driver', 'ticks': 600, 'late_ticks': 20,
                                 'stale_ticks': 0, 'clipped_commands': 0}}
    text = loop_text(report)
    assert text.startswith('the loop: estimates skipped 7 of 607, estimate stamp jumps 1, '
                           'estimator resets 2, tip dropouts 0; messages lost: /tip_positions 2, '
                           '/torque_commands 4; lab_driver: late ticks 20 of 600, stale ticks 0')
    assert 'give the loop its cores' in text        # the resets
    # a best-effort link's few lost messages and a few late ticks are not a troubled loop
    calm = loop_report(start, {**end, 'estimator': {'resets': '0'}, 'controller': {
        'estimates': '610', 'skipped_estimates': '9'}})
    assert 'give the loop its cores' not in loop_text(calm)
    late = loop_report(start, {**end, 'estimator': {}, 'controller': {'estimates': '610'},
                               'lab_driver': {'ticks': '1600', 'late_ticks': '40'}})
    assert late['driver']['late_ticks'] == 33 and 'give the loop its cores' in loop_text(late)
    # a driver that clipped the controller's commands: counted over the plan, said, and the fix
    clipped = loop_report(start, {**end, 'estimator': {'resets': '0'}, 'controller': {
        'estimates': '610', 'skipped_estimates': '9'}, 'lab_driver': {
        'ticks': '1600', 'late_ticks': '7', 'stale_ticks': '400', 'clipped_commands': '12'}})
    assert clipped['driver']['clipped_commands'] == 12
    assert 'stale ticks 0, clipped commands 12. The driver clipped commands: its bounds are ' \
        "narrower than the controller's" in loop_text(clipped)
    assert 'give the loop its cores' not in loop_text(clipped)
    assert 'clipped' not in loop_text(calm)
    # estimates refused for another task_dim, or none answered: said, and what to do
    refused = loop_report({}, {'controller': {'wrong_task_dim': '300'}})
    assert loop_text(refused).endswith('refused for another task_dim 300; messages lost: none. A '
                                       'node of another task_dim fed the controller (its log '
                                       "names it): give it the model's")
    assert loop_text(loop_report({}, {})).endswith(
        '. The controller answered no estimate: is the estimator running?')
    quiet = loop_report({}, {'controller': {'estimates': '600'}, 'recorder': {},
                             'trajectory': {'ticks': '600'}})
    assert quiet['driver'] is None and quiet['lost'] == {}
    assert loop_text(quiet) == ('the loop: estimates skipped 0 of 600, estimate stamp jumps 0, '
                                'estimator resets 0, tip dropouts 0; messages lost: none')


@pytest.mark.slow
def test_one_command_deploys_records_ends_with_the_plan_and_scores_it(tmp_path):
    env = ros_env()
    params = params_file(tmp_path / 'params.yaml')
    out = tmp_path / 'run'
    with Graph(env, tmp_path / 'driver_logs') as graph:
        graph.start('plant_driver', {'plant': 'tendon3', 'finger_names': NAMES, 'rate': 200.0},
                    params_file=None)
        r = _tool('--params', str(params), '--out', str(out), timeout=400, env=env)
        assert graph.procs['plant_driver'].alive()
    assert r.returncode == 0, r.stdout + r.stderr
    assert 'plan started: 3 s, 2 finger(s) with sdre_ff' in r.stdout
    score = json.loads((out / 'score.json').read_text())
    assert score['tips_topic'] == 'true_tip_positions' and score['plan_seconds'] == 3.0
    # the driver's true tips over the 3 s plan at 200 Hz: 600 on a quiet machine; a driver starved
    # of CPU ticks less (253 in a CI run beside the suite's other worker); that a recording loses
    # nothing is test_faults_procs'
    assert score['samples'] > 100 and score['commands'] > 0
    assert score['outside_bounds'] == 0 and len(score['rmse_mm']) == 2
    assert all(np.isfinite(score['rmse_pct_of_travel']))
    assert f'{score["rmse_pct_of_travel"]} % of the 2 mm travel' in r.stdout
    assert (out / 'bag').is_dir() and (out / 'logs' / 'controller.log').is_file()
    # what the loop counted over the plan, plant_driver's ticks among it, printed and kept
    loop = score['loop']
    assert loop['driver']['node'] == 'plant_driver' and loop['controller']['estimates'] > 100
    assert loop_text(loop).split('. A busy')[0] in r.stdout


@pytest.mark.parametrize('facts', [
    dict(travel=2e-3, torque_limit=0.02, direction=120.0),                   # the planar move
    dict(travel=3e-3, torque_limit=4.0, axis=(0.0, 0.6, 0.8),
         bounds=InputBounds([0.0] * 3, [4.0] * 3)),                          # a 3-D tip
])
def test_the_params_training_writes_hold_what_the_deployment_reads(tmp_path, facts):
    from soft_gripper_sdre.analysis import loop_settings as ls
    from soft_gripper_sdre.tools.graph.deploy import Settings
    from soft_gripper_sdre.tools.learning.train_bags import params_yaml
    facts = ls.DataFacts(period=5e-3, noise_std=5e-5, accel_psd_ml=1.0, **facts)
    settings = ls.LoopSettings(5e-3, 5e-5, 1.0, 1e6, 1e3, 1.0, facts.torque_limit, 50.0, 0.0,
                               1e-3, 1.0, 0.1, 2.0)
    path = tmp_path / 'params.yaml'
    if facts.d == 2:
        model, m = MODEL, 2
    else:                   # the deployment checks the nodes' task_dim against the model's
        from shaped_models import trained_known_system
        model, m = trained_known_system(3, 3, tmp_path)[2], 3
    path.write_text(params_yaml(ls.Derivation(settings, {}, [], facts, m=m), model, NAMES,
                                'bags'))
    plan = yaml.safe_load(path.read_text())['/**/trajectory']['ros__parameters']
    assert plan['finger_names'] == NAMES and plan['grasp_fingers'] == [0, 1]
    assert plan['others'] == 'hold'
    got = Settings(path)
    assert got.finger_names == NAMES and got.plan_seconds == 5.5 and got.rest_seconds == 0.5
    assert got.travel == pytest.approx(facts.travel, rel=1e-9) and got.d == facts.d
    assert got.bounds == (facts.bounds or InputBounds.symmetric(0.02, 2))


def test_a_symmetric_limit_reaches_the_deployment_on_every_input_of_the_model(tmp_path):
    """Symmetric bounds on other than two inputs, or beyond the controller's torque_limit range
    (inputs in N), are written as input_lower / input_upper; a torque_limit alone is taken on
    each input of the model at model_path."""
    from shaped_models import trained_known_system

    from soft_gripper_sdre.analysis import loop_settings as ls
    from soft_gripper_sdre.tools.graph.deploy import Settings, controller_bounds
    facts = ls.DataFacts(period=5e-3, noise_std=5e-5, accel_psd_ml=1.0, travel=2e-3,
                         torque_limit=0.02, direction=120.0)

    def controller(limit, m):
        settings = ls.LoopSettings(5e-3, 5e-5, 1.0, 1e6, 1e3, 1.0, limit, 50.0, 0.0, 1e-3, 1.0,
                                   0.1, 2.0)
        return ls.Derivation(settings, {}, [], facts, m=m).params(NAMES)['controller']

    assert controller(0.02, 2)['torque_limit'] == 0.02              # the hand's: as it was
    assert 'input_lower' not in controller(0.02, 2)
    for limit, m in ((0.02, 3), (0.02, 1), (40.0, 2)):
        ctrl = controller(limit, m)
        assert 'torque_limit' not in ctrl
        assert ctrl['input_lower'] == [-limit] * m and ctrl['input_upper'] == [limit] * m
    from soft_gripper_sdre.nodes.controller import PARAMS
    assert ls.TORQUE_LIMIT_RANGE == next((p.min, p.max) for p in PARAMS
                                         if p.name == 'torque_limit')
    # a params file holding only torque_limit: the bounds are on each of the model's inputs
    _, _, model = trained_known_system(3, 3, tmp_path)
    assert controller_bounds({'torque_limit': 0.5, 'model_path': str(model)},
                             tmp_path) == InputBounds.symmetric(0.5, 3)
    path = params_file(tmp_path / 'params.yaml', task_dim=3)
    data = yaml.safe_load(path.read_text())
    data['/**/controller']['ros__parameters']['model_path'] = str(model)
    data['/**/estimator']['ros__parameters']['task_dim'] = 3
    path.write_text(yaml.safe_dump(data))
    assert Settings(path).bounds == InputBounds.symmetric(0.02, 3)
