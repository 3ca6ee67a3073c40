"""tools.graph.foreign: the README's own-gripper recipe over DDS on a gripper unlike the package's
own (sim/plants/chain.py through the plant_driver node).

The end-to-end runs are marked serial: the driver node stands in for the lab's plant, and a plant
simulated in a process starved of CPU is not the plant (its late ticks step it over longer
periods, a stall past MAX_STEP_PERIODS slows its time). Beside the suite's other worker the
pneumatic finger's recordings fitted worse (free runs of 36-39 % of the motion, 12-13 % alone)
and its chambers' 40 and 60 ms lags read as 10 and 20 ms. The two grippers' recordings, which
take a quarter of the machine each, run side by side; their trainings and deployments do not."""
import json
import math
import os
from pathlib import Path
import re
import subprocess
import sys

import pytest
import yaml

from soft_gripper_sdre.analysis.bag_dataset import read_recording, settle_noise
from soft_gripper_sdre.sim.plants.presets import GRIPPERS, RATES
from soft_gripper_sdre.sim.shape import InputBounds, ShapeError
from soft_gripper_sdre.tools.graph import foreign
from soft_gripper_sdre.tools.learning.train_bags import RETRY_SCORE

ROOT = Path(__file__).resolve().parents[1]


TOOL = [sys.executable, '-m', 'soft_gripper_sdre.tools.graph.foreign']


def _tool(*args, timeout=60):
    return subprocess.run([*TOOL, *args], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, env={**os.environ, 'PYTHONUNBUFFERED': '1'})


@pytest.mark.parametrize('args, message', [
    (['--plant', 'soft9'], "invalid choice: 'soft9'"),
    (['--laws', 'bogus'], 'unknown law'),
    (['--seed', '-1'], '--seed must be'),
    (['--epochs', '0'], '--epochs must be >= 1'),
    (['--domain-id', '500'], '--domain-id must be'),
    (['--rollout-epochs', '-1'], '--rollout-epochs must be >= 0'),
    (['--bags', '/nonexistent/bags'], 'has no train/ and val/ bag directories'),
    (['--identify-only', '--bags', '/nonexistent/bags'], '--identify-only records new bags'),
])
def test_bad_arguments_exit_2_before_anything_starts(tmp_path, args, message):
    out = tmp_path / 'out'
    full = ['--out', str(out)] + (args if '--plant' in args else ['--plant', 'tendon3', *args])
    r = _tool(*full)
    assert r.returncode == 2 and message in r.stderr and 'Traceback' not in r.stderr
    assert not out.exists()


def test_the_amplitude_is_read_from_the_level_line_capped_by_the_bounds_or_not():
    """The excitation node's two forms of the level line (nodes/excitation_report.py)."""
    aimed = ('[excitation]: level of u1: probes … taken × 1, 1 for the whole signal (its measured '
             'response); amplitude 0.4649 for 8 mm, 0.0 % of the signals\' samples at the bounds')
    capped = ('[excitation]: level of u1: probes … (its measured response); amplitude 1.231 (the '
              'largest the input bounds allow) for about 6.20 mm of the 8 mm aimed at')
    assert foreign.chosen_amplitude(aimed) == 0.4649
    assert foreign.chosen_amplitude(capped) == 1.231
    assert foreign.chosen_amplitude('finished: 10.5 s played') is None


def test_every_gripper_has_its_lab_setup_and_one_sided_actuators_give_their_bounds():
    assert set(foreign.SETUPS) == set(GRIPPERS)
    assert all(foreign.SETUPS[k].rate == RATES[k] for k in GRIPPERS)
    assert foreign.SETUPS['pneumatic1'].rate == 100.0
    assert 200.0 <= foreign.SETUPS['trunk3'].rate <= 500.0
    assert foreign.actuator_bounds('tendon3') == {} == foreign.actuator_bounds('stiff2')
    assert foreign.actuator_bounds('pneumatic1') == {'input_lower': [0.0],
                                                     'input_upper': [60e3]}
    assert foreign.actuator_bounds('trunk3') == {'input_lower': [0.0] * 3,
                                                 'input_upper': [4.0] * 3}
    # training is given every driver's bounds
    assert foreign.driver_bounds('stiff2') == {'input_lower': [-0.25] * 2,
                                               'input_upper': [0.25] * 2}
    assert foreign.driver_bounds('trunk3') == foreign.actuator_bounds('trunk3')


def test_the_training_command_is_the_readmes_for_each_gripper(tmp_path):
    """A 3-D tip (trunk3) is trained with --task-dim 3 (README: a 3-D tip: --task-dim 3), the
    planar grippers with the default; every gripper gives its driver's bounds."""
    def command(plant, *extra):
        a = foreign._parser().parse_args(['--plant', plant, '--out', str(tmp_path / 'o'), *extra])
        return foreign.train_command(a, tmp_path / 'bags', tmp_path / 'o')

    trunk = command('trunk3')
    assert trunk[trunk.index('--task-dim') + 1] == '3'
    assert trunk[trunk.index('--input-upper') + 1:] == ['4.0'] * 3
    assert trunk[trunk.index('--bag') + 1] == str(tmp_path / 'bags' / 'train')
    for plant in ('tendon3', 'stiff2', 'pneumatic1'):
        assert '--task-dim' not in command(plant)
    tendon = command('tendon3')
    assert tendon[tendon.index('--input-lower') + 1:][:2] == ['-0.02'] * 2
    tail = command('stiff2', '--epochs', '5', '--rollout-epochs', '0')[-4:]
    assert tail == ['--epochs', '5', '--rollout-epochs', '0']


def test_the_controller_bounds_come_from_the_parameter_file(tmp_path):
    params = tmp_path / 'params.yaml'
    ctrl = {'torque_limit': 0.05}
    params.write_text(yaml.safe_dump({'/**/controller': {'ros__parameters': ctrl}}))
    assert foreign.controller_bounds(params, 2) == InputBounds.symmetric(0.05, 2)
    ctrl.update(input_lower=[0.0], input_upper=[3e4])
    params.write_text(yaml.safe_dump({'/**/controller': {'ros__parameters': ctrl}}))
    assert foreign.controller_bounds(params, 1) == InputBounds([0.0], [3e4])
    with pytest.raises(ShapeError, match='params.yaml: input_lower/input_upper: the finger has 3'):
        foreign.controller_bounds(params, 3)


def test_an_existing_output_is_never_overwritten(tmp_path):
    (tmp_path / 'keep.txt').write_text('mine')
    r = _tool('--plant', 'stiff2', '--out', str(tmp_path))
    assert r.returncode == 2 and 'exists already' in r.stderr
    assert (tmp_path / 'keep.txt').read_text() == 'mine'


def _miss(out: Path, metrics: dict) -> str:
    """What a missed grasp needs to be told apart: the score with what the loop's nodes counted
    meanwhile (a starved driver's late ticks, lost messages, skipped estimates), the settings and
    what training expected of them, and the last warning of each kind from each node."""
    derived = metrics['training']['derived_settings']
    settings = {k: derived['settings'][k] for k in ('bandwidth_hz', 'accel_psd', 'integral_gain')}
    expected = {'model': derived['checks']['sdre_ff']['rmse_rel'], 'score': derived.get('score'),
                **{f: c['rmse_rel'] for f, c in (derived.get('on_fingers') or {}).items()}}
    warnings = {}
    for log in sorted((out / 'deploy_sdre_ff' / 'logs').glob('*.log')):
        last = {}       # the last warning of each kind (its first words, numbers aside)
        for line in log.read_text().splitlines():
            if '[WARN]' in line or '[ERROR]' in line:
                text = line.split(']: ', 1)[-1]
                last[re.sub(r'[\d.]+', '#', text)[:24]] = text[:240]
        if last:
            warnings[log.stem] = list(last.values())
    return (f"score {metrics['deploy']['sdre_ff']}; settings {settings}; error / travel "
            f"expected on the model and the fingers' own fits {expected}; free run "
            f"{metrics['training']['fitness'].get('free_run')}; warnings {warnings}")


def _identified_side_by_side(tmp_path: Path) -> dict[str, Path]:
    """Step 1 of the tendon and the one-chamber grippers' recipes at once (``--identify-only``),
    each on a domain of its own (the tool claims a free one when ``ROS_DOMAIN_ID`` is unset: on
    one domain each run's excitation hears the other's tips): a recording takes about a quarter
    of the two cores (its driver, the excitation node and the recorder), so two leave each driver
    the CPU it needs; training, which takes both cores, and deploying come after, one gripper at
    a time. Each run's directory."""
    runs = {plant: tmp_path / f'{plant}_identified' for plant in ('tendon3', 'pneumatic1')}
    env = {k: v for k, v in os.environ.items() if k != 'ROS_DOMAIN_ID'}
    procs = {plant: subprocess.Popen(
        [*TOOL, '--plant', plant, '--out', str(out), '--identify-only'], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**env, 'PYTHONUNBUFFERED': '1'})
        for plant, out in runs.items()}
    for plant, proc in procs.items():
        _, err = proc.communicate(timeout=900)
        assert proc.returncode == 0, (plant, err[-3000:])
        assert not (runs[plant] / 'model').exists()          # step 1 only: nothing trained
    return runs


@pytest.mark.slow
@pytest.mark.serial
@pytest.mark.ros
@pytest.mark.timeout(2700)
def test_the_recipe_runs_end_to_end_on_the_tendon_and_the_one_chamber_fingers(tmp_path):
    """The recipe over DDS on a two-torque finger and a one-input finger, each identified from a
    best-effort, wall-stamped driver (side by side), then trained and deployed on those bags
    (``--bags``): :func:`_tendon_trained_and_deployed`, :func:`_pneumatic_trained_and_deployed`."""
    identified = _identified_side_by_side(tmp_path)
    _tendon_trained_and_deployed(tmp_path / 'tendon3', identified['tendon3'])
    _pneumatic_trained_and_deployed(tmp_path / 'pneumatic1', identified['pneumatic1'])


def _tendon_trained_and_deployed(out: Path, identified: Path) -> None:
    """The 200 Hz tendon finger: every bag holds its settle phase and the measured noise, the
    level search chose an amplitude, the model is judged fit, the checked move follows the travel
    rule, and a deployed grasp tracks without saturating at rest. The preset's full training, as
    the README runs it (about 20 s here; trained 40 + 10 epochs, one CI run's recordings gave a
    model whose free run missed by 69 %, not fit, where the full preset's is fit and tracked within
    1.1 / 1.0 % over DDS)."""
    r = _tool('--plant', 'tendon3', '--out', str(out), '--bags', str(identified / 'bags'),
              '--laws', 'sdre_ff', timeout=1400)
    assert r.returncode in (0, 1), r.stderr[-3000:]
    metrics = json.loads((out / 'metrics.json').read_text())
    identification = json.loads((identified / 'metrics.json').read_text())['identification']
    bags = identified / 'bags'
    assert all(0 < a < 1 for a in identification['amplitude'].values())
    bags = sorted((bags / 'train').glob('*/metadata.yaml')) + \
        sorted((bags / 'val').glob('*/metadata.yaml'))
    assert len(bags) == 6
    for meta in bags:
        rec = read_recording(meta.parent)
        assert rec.finger_names == ('index', 'thumb')
        for finger in range(2):
            # the excitation node answers at least settle_samples (100) tips with zero torque
            # before the first non-zero one, however late the driver's ticks come; the recorder
            # hears the same best-effort tips (a few may be lost)
            _, sigma, n = settle_noise(rec, finger)
            assert n >= 90 and 3e-5 < sigma < 7e-5           # the driver's 0.05 mm
    training = metrics['training']
    assert training['fitness']['fit_for_control'], training['fitness']['reasons']
    derived = training['derived_settings']
    facts = derived['facts']
    # the move is what the model holds with half the torque limit, within half the data's reach
    assert 10 * facts['noise_std'] <= facts['travel'] <= facts['reach_travel']
    if r.returncode == 1:  # no setting passed its check: said, nothing written
        assert derived['settings'] is None and derived['candidates']
        assert not (out / 'model' / 'params.yaml').exists()
        assert 'no controller setting passed' in r.stderr
        return
    # the loop runs at the bags' tip period: the driver's 200 Hz, its ticks a little late on a
    # loaded machine (a median of 5.33 ms in one CI run beside other work)
    assert derived['settings']['control_period'] == facts['period']
    assert facts['period'] == pytest.approx(1 / 200, rel=0.1)
    # the move goes the way the finger bends (up and in: the inputs' common direction, 120–140°),
    # and params.yaml gives it to the trajectory node
    assert 110 < facts['direction'] < 150
    plan = yaml.safe_load((out / 'model' / 'params.yaml').read_text())['/**/trajectory'][
        'ros__parameters']
    assert (math.hypot(plan['close_distance'], plan['side_distance'])
            == pytest.approx(facts['travel']))
    assert math.degrees(math.atan2(plan['close_distance'], plan['side_distance'])) == \
        pytest.approx(facts['direction'])
    assert plan['contact_distance'] == plan['close_distance']
    # the paper's law's offset against the spring, and the loop it would need to hold a tenth
    paper = derived['paper_law']
    assert 0 < paper['hold_offset'] < 1
    assert (paper['hold_offset'] > paper['share']) == \
        (paper['needs_bandwidth_hz'] is None
         or paper['needs_bandwidth_hz'] > derived['settings']['bandwidth_hz'])
    # its fits find no lag: the draws go by the settings' score on the model, drawn again over
    # RETRY_SCORE, the lowest kept (docs/own_gripper.md, "Draws")
    model_metrics = json.loads((out / 'model' / 'metrics.json').read_text())
    draws = model_metrics['draws']
    assert derived['score'] == min(d['score'] for d in draws if d['settings'])
    assert all(d['expected_rmse_rel'] is None for d in draws)
    assert all(not d['settings'] or d['score'] > RETRY_SCORE for d in draws[:-1])
    assert model_metrics['seed'] == min(draws, key=lambda d: (
        not d['settings'], d['score'] if d['settings'] else math.inf, d['seed']))['seed']
    score = metrics['deploy']['sdre_ff']
    assert metrics['deploy']['travel'] == facts['travel']
    assert score['samples'] > 500 and score['saturated_at_rest'] == 0.0
    assert score['loop']['driver']['node'] == 'plant_driver'      # counted over the plan
    assert score['loop']['controller']['estimates'] > 500
    # the model pooled from both fingers, with each finger's input gain: index / thumb
    # 1.1 / 1.0 % of travel on one CI run's recordings; bounded at twice the recipe's 5 % target
    assert max(score['rmse_pct_of_travel']) < 10.0, _miss(out, metrics)


def _pneumatic_trained_and_deployed(out: Path, identified: Path) -> None:
    """A finger of one input (a chamber, 0 to 60 kPa, a pressure lag) and a planar tip at 100 Hz:
    the excitation and training get the chamber's bounds, the model has shape (2, 1), the checked
    move follows the curve of the model's equilibria (params.yaml's close_path), and the deployed
    grasp never commands outside the bounds nor sits at a bound other than the vented chamber at
    rest. The preset's full training (trained 40 + 10 epochs, the model's rest drifted off: not
    fit). Training finds each chamber's pressure lag in its own fit (the valves' 40 and 60 ms as
    50-60 and 80 ms) and checks the candidates on those fits; the deployed grasp tracked within
    4.2 % of travel over DDS on a quiet machine (docs/own_gripper.md), bounded here at twice
    that."""
    r = _tool('--plant', 'pneumatic1', '--out', str(out), '--bags', str(identified / 'bags'),
              '--laws', 'sdre_ff', timeout=1700)
    assert r.returncode in (0, 1), r.stderr[-3000:]
    metrics = json.loads((out / 'metrics.json').read_text())
    identification = json.loads((identified / 'metrics.json').read_text())['identification']
    bags = identified / 'bags'
    assert all(0 < a <= 1 for a in identification['amplitude'].values())
    for meta in sorted(bags.glob('*/*/metadata.yaml')):
        rec = read_recording(meta.parent)
        assert rec.n_inputs == 1
        u = rec.torques.reshape(-1)
        assert u.min() >= 0.0 and u.max() <= 60e3                  # the chamber only pushes
    training = metrics['training']
    assert training['fitness']['fit_for_control'], training['fitness']['reasons']
    derived = training['derived_settings']
    facts = derived['facts']
    if r.returncode == 1:
        assert derived['settings'] is None
        assert not (out / 'model' / 'params.yaml').exists()
        return
    assert len(facts['path']) >= 2 and facts['bounds']['lower'] == [0.0]
    assert 0 < facts['bounds']['upper'][0] <= 60e3
    params = yaml.safe_load((out / 'model' / 'params.yaml').read_text())
    plan = params['/**/trajectory']['ros__parameters']
    waypoints = plan['close_path']
    assert len(waypoints) == 2 * (len(facts['path']) - 1)
    assert plan['close_distance'] == pytest.approx(facts['travel'])
    ctrl = params['/**/controller']['ros__parameters']
    assert ctrl['input_lower'] == [0.0] and ctrl['input_upper'] == facts['bounds']['upper']
    score = metrics['deploy']['sdre_ff']
    # the plan's 5.5 s of true tips at 100 Hz, best effort (551 of 551 in two serial CI runs; a
    # driver starved beside other work thins them: 190 in a run beside the suite's other worker)
    assert score['samples'] > 300 and score['commands'] > 200
    assert score['outside_bounds'] == 0 and score['outside_plant_bounds'] == 0
    assert score['saturated_at_rest'] == 0.0
    model_metrics = json.loads((out / 'model' / 'metrics.json').read_text())
    fits = model_metrics['finger_fits']
    assert [f['finger'] for f in fits] == foreign.FINGERS
    assert all(0.02 <= f['lag_s'] <= 0.12 and f['free_run'] < 0.5 for f in fits), fits
    # each chamber's static gain against the pooled model (0.87 / 1.06 in the runs measured),
    # carried into the controller's parameters in the fingers' order
    gains = model_metrics['input_gains']
    assert [g['finger'] for g in gains] == foreign.FINGERS
    assert all(0.7 < g['gain'] < 1.4 for g in gains), gains
    assert ctrl['input_gains'] == [g['gain'] for g in gains]
    # what the fits with their lags expect of the chosen settings: kept and said
    expected = derived['on_fingers']
    assert list(expected) == foreign.FINGERS
    assert "on the fingers' own fits, each with its input lag" in (out / 'train.log').read_text()
    # each training drawn is said and kept; the kept one's expectation is the one above
    draws = model_metrics['draws']
    assert 1 <= len(draws) <= 3
    assert model_metrics['seed'] == min(draws, key=lambda d: (
        not d['settings'], d['expected_rmse_rel'] if d['expected_rmse_rel'] is not None
        else math.inf, d['score'] if d['settings'] else math.inf, d['seed']))['seed']
    assert max(score['rmse_pct_of_travel']) < 10.0, _miss(out, metrics)
