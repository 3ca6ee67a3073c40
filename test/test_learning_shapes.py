"""The learned model and its training for fingers of any shape (d, m): real torch training on
known SDC systems of shapes (2, 1), (3, 3) and (2, 3), checkpoints that carry the shape and the
input bounds, and every bad shape, bag and command-line value refused by name."""
from dataclasses import replace
import re

from bag_writing import MS, tips_messages, write_bag
from known_systems import DAMPING, STIFFNESS, SYSTEMS, fit, system_data
import numpy as np
import pytest
import torch

from soft_gripper_sdre.analysis.bag_dataset import (
    BagDataError,
    read_recording,
    recorded_bounds,
    task_dimension,
    torque_joint_order,
)
from soft_gripper_sdre.learning.model import (
    DEFAULT_MODEL,
    ModelFileError,
    SDCModel,
    SDCNet,
    read_checkpoint,
)
from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import save_checkpoint, train
from soft_gripper_sdre.sim.shape import HAND_SHAPE, FingerShape, InputBounds, ShapeError
from soft_gripper_sdre.tools.learning import train as train_tool
from soft_gripper_sdre.tools.learning.train_bags import (
    _label_sets,
    finger_shape,
    load_bags,
    runs,
)


@pytest.fixture(scope='module', params=list(SYSTEMS), ids=lambda s: f'd{s[0]}m{s[1]}')
def trained(request, tmp_path_factory):
    """(shape, result, settings, data, the checkpoint written with the system's bounds)."""
    d, m = request.param
    result, settings, data = fit(d, m)
    path = tmp_path_factory.mktemp('shape') / 'model.pt'
    save_checkpoint(path, result, rest_tip=np.array([0.01, -0.02, 0.03]), dt=1e-3,
                    settings=settings, data={'source': 'test'}, input_bounds=SYSTEMS[(d, m)][1])
    return FingerShape(d, m), result, settings, data, path


def test_the_networks_are_sized_by_the_shape(trained):
    shape, result, *_ = trained
    d, m = shape.d, shape.m
    net = result.net
    assert net.a_net[0].in_features == 2 * d and net.a_net[4].out_features == 2 * d * d
    assert net.g_net[0].in_features == 2 * d and net.g_net[4].out_features == d * m
    a, g = net(torch.zeros(5, 2 * d))
    assert a.shape == (5, d, 2 * d) and g.shape == (5, d, m)
    assert net.accel(torch.zeros(5, 2 * d), torch.zeros(5, m)).shape == (5, d)


def test_training_lowers_the_loss_and_finds_the_input_directions(trained):
    """Each learned column of G2 at the mid-level state points where the true one does (cosine
    > 0.9), and the validation loss fell well below the untrained network's."""
    shape, result, _, data, path = trained
    G2_true, bounds = SYSTEMS[(shape.d, shape.m)]
    assert min(result.val_loss) < 0.2 * result.val_loss[0]
    model = SDCModel(path)
    x = data[3][:200]
    _, G2 = model.sdc_blocks(x)
    G2 = G2.mean(axis=0)
    for k in range(shape.m):
        cos = G2[:, k] @ G2_true[:, k] / np.linalg.norm(G2[:, k]) / np.linalg.norm(G2_true[:, k])
        assert cos > 0.9, (k, G2[:, k], G2_true[:, k])
        assert 0.5 < np.linalg.norm(G2[:, k]) / np.linalg.norm(G2_true[:, k]) < 2.0


def test_the_checkpoint_round_trips_the_shape_bounds_and_networks(trained):
    shape, result, _, data, path = trained
    ckpt = read_checkpoint(path)
    assert ckpt['shape'] == shape and ckpt['input_bounds'] == SYSTEMS[(shape.d, shape.m)][1]
    assert ckpt['architecture']['n_state'] == shape.n_state
    model = SDCModel(path)
    assert model.shape == shape and model.input_bounds == SYSTEMS[(shape.d, shape.m)][1]
    for k, v in result.net.state_dict().items():
        assert torch.equal(ckpt['state_dict'][k], v), k
    x, u = data[3][:50], data[4][:50]
    A, G = model.AG(x)
    n, d = shape.n_state, shape.d
    assert A.shape == (50, n, n) and G.shape == (50, n, shape.m)
    np.testing.assert_array_equal(A[:, :d, :d], 0.0)
    np.testing.assert_array_equal(A[:, :d, d:], np.broadcast_to(np.eye(d), (50, d, d)))
    np.testing.assert_array_equal(G[:, :d], 0.0)
    # the fused numpy network is the torch networks run in double, physical units
    net = ckpt['net'].double()
    s = {k: v.numpy() for k, v in ckpt['scales'].items()}
    with torch.no_grad():
        a, g = (t.numpy() for t in net(torch.as_tensor(x / s['x'])))
    A2, G2 = model.sdc_blocks(x)
    np.testing.assert_allclose(A2, a * s['acc'][:, None] / s['x'][None, :], rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_allclose(G2, g * s['acc'][:, None] / s['u'][None, :], rtol=1e-12,
                               atol=1e-12)
    w1, b1, w2, b2, w3, b3 = model.fused_network
    assert w1.shape[0] == n and w3.shape[1] == 2 * d * d + d * shape.m
    np.testing.assert_allclose(model.xdot(x, u)[:, :d], x[:, d:], rtol=0, atol=0)
    np.testing.assert_array_equal(model.xdot(np.zeros(n), np.zeros(shape.m)), 0.0)
    with pytest.raises(ValueError, match=rf'x must have shape \({n},\)'):
        model.AG(np.zeros(n + 1))


def test_the_simulation_stage_runs_for_any_shape():
    """The rollout epochs on records of a (3, 3) finger: positions of three coordinates driven by
    three held inputs, every epoch's validation simulation error finite."""
    from soft_gripper_sdre.learning.rollout import Run
    d, m = 3, 3
    G2, bounds = SYSTEMS[(d, m)]
    rng = np.random.default_rng(3)
    dt, steps = 2e-3, 600
    u = np.repeat(bounds.lower + bounds.half_span * 2 * rng.random((steps // 20, m)), 20, axis=0)
    x = np.zeros((steps, 2 * d))
    acc = np.zeros((steps, d))
    for k in range(steps - 1):                      # semi-implicit Euler of the known system
        acc[k] = -STIFFNESS * x[k, :d] - DAMPING * x[k, d:] + G2 @ u[k]
        x[k + 1, d:] = x[k, d:] + dt * acc[k]
        x[k + 1, :d] = x[k, :d] + dt * x[k + 1, d:]
    acc[-1] = -STIFFNESS * x[-1, :d] - DAMPING * x[-1, d:] + G2 @ u[-1]
    half = steps // 2
    settings = replace(PRESETS['gripper'], epochs=5, rollout_epochs=3, rollout_val_seconds=0.2)
    result = train(x[:half], u[:half], acc[:half], x[half:], u[half:], acc[half:], settings,
                   runs=[Run(x[:half], u[:half], dt)], val_runs=[Run(x[half:], u[half:], dt)],
                   shape=FingerShape(d, m))
    assert len(result.rollout_loss) == 3 and len(result.val_sim_error) == 8
    assert np.all(np.isfinite(result.val_sim_error)) and np.all(np.isfinite(result.rollout_loss))


def test_the_rest_penalty_moves_a_3d_rest_left():
    """L_rest of a (3, 3) network: positive while A(0) (6 × 6) has an eigenvalue right of the
    margin, and its gradient steps move the rightmost eigenvalue left."""
    from soft_gripper_sdre.learning.rollout import Scales
    from soft_gripper_sdre.learning.training import _rest_penalty
    torch.manual_seed(0)
    net = SDCNet(shape=FingerShape(3, 3))
    s = Scales(torch.full((6,), 0.1), torch.ones(3), torch.full((3,), 10.0))
    settings = replace(PRESETS['default'], rest_margin=50.0)

    def rightmost():
        with torch.no_grad():
            a0 = net(torch.zeros(1, 6))[0][0] * s.acc[:, None] / s.x[None, :]
        A0 = np.vstack([np.hstack([np.zeros((3, 3)), np.eye(3)]), a0.numpy()])
        return np.linalg.eigvals(A0).real.max()

    before = rightmost()
    assert before > -50.0
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(30):
        loss = _rest_penalty(net, s, settings)
        assert loss is not None and float(loss.detach()) > 0
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert rightmost() < before - 1.0


def test_the_singular_value_penalty_runs_on_a_non_square_g2():
    result, *_ = fit(2, 3, epochs=2, sv_penalty=1.0)
    assert len(result.train_loss) == 2 and np.all(np.isfinite(result.train_loss))


def test_train_refuses_arrays_of_another_shape():
    x, u, acc = system_data(3, 3, 100, 0)
    with pytest.raises(ValueError, match=r'u must have shape \(N, 3\) for the shape d=3, m=3'):
        train(x, u[:, :2], acc, x, u, acc, PRESETS['default'], shape=FingerShape(3, 3))
    with pytest.raises(ValueError, match=r'x must have shape \(N, 4\) for the shape d=2, m=2'):
        train(x, u, acc, x, u, acc, PRESETS['default'])


def test_the_hand_network_is_the_default_shape():
    """SDCNet() is the hand's, seeded alike: the same initial weights as SDCNet(shape=HAND)."""
    torch.manual_seed(0)
    a = SDCNet().state_dict()
    torch.manual_seed(0)
    b = SDCNet(shape=HAND_SHAPE).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert SDCNet().a_net[4].out_features == 8 and SDCNet().g_net[4].out_features == 4


def test_the_shipped_model_is_the_hands_without_bounds():
    ckpt = read_checkpoint(DEFAULT_MODEL)
    assert ckpt['shape'] == HAND_SHAPE and ckpt['input_bounds'] is None
    assert 'shape' not in torch.load(DEFAULT_MODEL, weights_only=True)   # an older checkpoint
    assert SDCModel().shape == HAND_SHAPE and SDCModel().input_bounds is None


# -- bad checkpoints ---------------------------------------------------------------------------

def _resave(tmp_path, source, edit):
    path = tmp_path / 'bad.pt'
    torch.save(edit(torch.load(source, weights_only=True)), path)
    return path


BAD_SHAPES = {
    'task dimension 4': (lambda c: {**c, 'shape': {'d': 4, 'm': 1}}, 'shape: the task dimension d'),
    'no inputs': (lambda c: {**c, 'shape': {'d': 2, 'm': 0}}, 'shape: the number of inputs m'),
    'shape not a mapping': (lambda c: {**c, 'shape': [2, 1]}, 'shape: expected a mapping'),
    'shape of other declared sizes': (
        lambda c: {**c, 'shape': {'d': 3, 'm': 3}, 'input_bounds': None},
        r'does not match the network layout: architecture n_state = 4, the shape \(d=3, m=3\)'),
    'shape of other weights': (
        lambda c: {**c, 'shape': {'d': 3, 'm': 1}, 'architecture': {'hidden': 32}},
        '(?s)does not match the network layout: .*size mismatch'),
    'bounds of another shape': (lambda c: {**c, 'shape': {'d': 3, 'm': 3}},
                                r'input_bounds name 1 input\(s\), the shape \(d=3, m=3\) has 3'),
    'declared sizes of another shape': (
        lambda c: {**c, 'architecture': {**c['architecture'], 'n_input': 2}},
        'architecture n_input = 2, the shape'),
    'bounds of another input count': (
        lambda c: {**c, 'input_bounds': {'lower': [0.0, 0.0], 'upper': [1.0, 1.0]}},
        'input_bounds name 2 input'),
    'empty bounds': (lambda c: {**c, 'input_bounds': {'lower': [1.0], 'upper': [0.0]}},
                     'input_bounds: .*lower bound must be below'),
    'bounds not a mapping': (lambda c: {**c, 'input_bounds': [0.0, 1.0]},
                             'input_bounds: expected a mapping'),
    'input scale of another shape': (
        lambda c: {**c, 'scales': {**c['scales'], 'u': torch.ones(2, dtype=torch.float64)}},
        r'scale u has shape \(2,\), the shape \(d=2, m=1\) needs \(1,\)'),
}


@pytest.fixture(scope='module')
def one_input_checkpoint(tmp_path_factory):
    result, settings, _ = fit(2, 1, epochs=1)
    path = tmp_path_factory.mktemp('one') / 'model.pt'
    save_checkpoint(path, result, rest_tip=np.zeros(3), dt=1e-2, settings=settings, data={},
                    input_bounds=SYSTEMS[(2, 1)][1])
    return path


@pytest.mark.parametrize('case', list(BAD_SHAPES))
def test_a_bad_or_inconsistent_shape_is_refused_naming_it(case, one_input_checkpoint, tmp_path):
    edit, match = BAD_SHAPES[case]
    path = _resave(tmp_path, one_input_checkpoint, edit)
    with pytest.raises(ModelFileError, match=match) as exc:
        read_checkpoint(path)
    assert str(path) in str(exc.value)
    with pytest.raises(ModelFileError):
        SDCModel(path)


def test_save_checkpoint_refuses_bounds_of_another_input_count(tmp_path):
    result, settings, _ = fit(2, 1, epochs=1)
    with pytest.raises(ValueError, match='input_bounds name 2 input'):
        save_checkpoint(tmp_path / 'm.pt', result, rest_tip=np.zeros(3), dt=1e-2,
                        settings=settings, data={}, input_bounds=InputBounds.symmetric(1.0, 2))
    assert not (tmp_path / 'm.pt').exists()


# -- bags of other shapes ----------------------------------------------------------------------

REST = np.array([0.004, -0.03, 0.012])


def shape_bag(path, d: int = 3, m: int = 1, seconds: float = 3.0, settle: float = 0.3,
              names=None, planar_z: float = 0.0, seed: int = 0):
    """A recording of a known finger of shape (d, m) at 1 kHz: a settle phase at zero input, then
    one-sided steps (0 to 2 per input) held 50 ms; tips = rest + p + 2 µm noise (a planar finger
    publishes z = ``planar_z`` throughout)."""
    G2 = {(3, 1): np.array([[0.4], [-0.2], [0.3]]), (2, 1): np.array([[0.4], [-0.2]]),
          (3, 3): SYSTEMS[(3, 3)][0], (2, 2): np.array([[0.0, 0.5], [-0.5, 0.0]])}[(d, m)]
    rng = np.random.default_rng(seed)
    n = int(seconds * 1000)
    dt = 1e-3
    u = np.repeat(2.0 * rng.random((n // 50 + 1, m)), 50, axis=0)[:n]
    u[:int(settle * 1000)] = 0.0
    p, v = np.zeros(d), np.zeros(d)
    tips = np.zeros((n, 1, 3))
    tips[:, 0, 2] = planar_z
    for k in range(n):
        tips[k, 0, :d] = REST[:d] + p + 2e-6 * rng.standard_normal(d)
        a = -STIFFNESS * p - DAMPING * v + G2 @ u[k]
        v = v + dt * a
        p = p + dt * v
    stamps = np.arange(n) * MS
    return write_bag(path, {'/tip_positions': tips_messages(stamps, tips),
                            '/torque_commands': _commands(stamps, u, names)})


def _commands(stamps, u, names=None):
    """JointState per row of u (C, m): one finger, names finger_0/ax0 … unless given."""
    from bag_writing import JOINT_STATE, T, _header
    m = u.shape[1]
    joint = names or [f'finger_0/ax{k}' for k in range(m)]
    return [(int(ns), T[JOINT_STATE](header=_header(ns), name=list(joint),
                                     position=np.empty(0), velocity=np.empty(0),
                                     effort=row.copy()))
            for ns, row in zip(stamps, u)]


def test_torque_names_give_the_number_of_inputs():
    assert torque_joint_order(['a/ax0']) == ['a/ax0']
    assert torque_joint_order(['b/ax2', 'a/ax0', 'b/ax1', 'a/ax2', 'a/ax1', 'b/ax0']) == [
        'b/ax0', 'b/ax1', 'b/ax2', 'a/ax0', 'a/ax1', 'a/ax2']
    for bad in (['a/ax0', 'a/ax2'], ['a/ax1'], ['a/ax0', 'a/ax1', 'b/ax0'],
                [f'a/ax{k}' for k in range(5)], ['left', 'right'], []):
        assert torque_joint_order(bad) == [], bad


def test_a_one_input_3d_bag_is_read_with_its_shape(tmp_path):
    rec = read_recording(shape_bag(tmp_path / 'b', d=3, m=1))
    assert rec.n_inputs == 1 and rec.torques.shape[1:] == (1, 1) and rec.z_moves()
    assert rec.finger_names == ('finger_0',) and rec.joint_names == ('finger_0/ax0',)
    assert task_dimension([rec]) == 3 and task_dimension([rec], 2) == 2
    bounds = recorded_bounds([rec])
    assert bounds.lower[0] == 0.0 and 1.9 < bounds.upper[0] <= 2.0 and bool(bounds.one_sided[0])
    assert rec.describe()['n_inputs'] == 1


def test_planar_tips_are_d_2_and_refuse_d_3(tmp_path):
    rec = read_recording(shape_bag(tmp_path / 'b', d=2, m=1, planar_z=0.0))
    assert not rec.z_moves() and task_dimension([rec]) == 2
    with pytest.raises(BagDataError, match=r"task dimension 3, but no tip's z moves in .*b"):
        task_dimension([rec], 3)


def test_a_one_input_3d_bag_trains_a_model_of_its_shape(tmp_path):
    """Bags of a known (3, 1) finger: labels by KF + RTS on x, y and z, a real training run, the
    checkpoint with the shape and the recorded bounds; the learned column points along the
    finger's."""
    train_bag = shape_bag(tmp_path / 'train', seconds=3.0, seed=0)
    val_bag = shape_bag(tmp_path / 'val', seconds=2.0, seed=1)
    train_set = load_bags([train_bag], 'tip_positions', 'torque_commands', 1.0, None)
    val_set = load_bags([val_bag], 'tip_positions', 'torque_commands', 1.0, None)
    shape, bounds = finger_shape(train_set, val_set, 'auto')
    assert shape == FingerShape(3, 1) and bounds.lower[0] == 0.0
    data = _label_sets(train_set, val_set, 1e4, None, shape, bounds)
    assert data.x.shape[1] == 6 and data.u.shape[1] == 1 and data.acc.shape[1] == 3
    np.testing.assert_allclose(data.rest_tip, REST, atol=2e-6)     # the settle phase's mean
    torch.set_num_threads(1)
    settings = replace(PRESETS['default'], epochs=40)
    result = train(data.x, data.u, data.acc, data.x_val, data.u_val, data.acc_val, settings,
                   runs=runs(data.samples), val_runs=runs(data.val_samples), shape=shape)
    path = save_checkpoint(tmp_path / 'model.pt', result, rest_tip=data.rest_tip, dt=data.dt,
                           settings=settings, data=data.info('tip_positions', 'torque_commands'),
                           input_bounds=bounds)
    model = SDCModel(path)
    assert model.shape == shape and model.input_bounds == bounds
    assert model.data['shape'] == {'d': 3, 'm': 1}
    g = model.sdc_blocks(np.zeros(6))[1][0, :, 0]
    true = np.array([0.4, -0.2, 0.3])
    assert g @ true / np.linalg.norm(g) / np.linalg.norm(true) > 0.9


def test_bags_of_different_input_counts_are_refused_naming_both(tmp_path):
    one = load_bags([shape_bag(tmp_path / 'one', d=3, m=1)], 'tip_positions', 'torque_commands',
                    1.0, None)
    three = load_bags([shape_bag(tmp_path / 'three', d=3, m=3)], 'tip_positions',
                      'torque_commands', 1.0, None)
    with pytest.raises(BagDataError, match=r"three commands 3 input\(s\) per finger "
                                           r".*finger_0/ax2.*one 1 \(\['finger_0/ax0'\]\)"):
        finger_shape(one, three)


def test_commands_of_more_fingers_than_tips_are_refused(tmp_path):
    """Two fingers of one input each named, one tip: not one finger of two inputs."""
    bag = shape_bag(tmp_path / 'two', d=2, m=2, names=['finger_0/ax0', 'finger_1/ax0'])
    with pytest.raises(BagDataError, match=r"names \['finger_0/ax0', 'finger_1/ax0'\]; "
                                           r"expected .* for each of the 1 finger"):
        read_recording(bag)


def test_commands_with_a_gap_in_the_input_numbers_are_refused(tmp_path):
    bag = shape_bag(tmp_path / 'gap', d=2, m=2, names=['finger_0/ax0', 'finger_0/ax2'])
    with pytest.raises(BagDataError, match=r"names \['finger_0/ax0', 'finger_0/ax2'\]; "
                                           r"expected '<finger>/ax0' … '<finger>/ax<m-1>'"):
        read_recording(bag)


# -- the train tool's shape arguments ----------------------------------------------------------

@pytest.fixture(scope='module')
def one_input_bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('bags')
    return shape_bag(root / 'train', d=2, m=1, seed=0), shape_bag(root / 'val', d=2, m=1, seed=1)


BAD_ARGS = {
    'lower without upper': (['--input-lower', '0'],
                            '--input-lower and --input-upper go together'),
    'two bounds for one input': (['--input-lower', '0', '0', '--input-upper', '2', '2'],
                                 '--input-lower/--input-upper: the finger has 1 input'),
    'empty interval': (['--input-lower', '2', '--input-upper', '0'],
                       'input ax0: the lower bound must be below the upper one'),
    'not finite': (['--input-lower', 'nan', '--input-upper', '2'], 'bounds must be finite'),
    'commands outside': (['--input-lower', '0', '--input-upper', '1'],
                         r'--input-lower/--input-upper: bag .*train commands input ax0 '
                         r'.*, outside \[0, 1\]'),
    'planar tips as 3-D': (['--task-dim', '3'], "task dimension 3, but no tip's z moves"),
    'task dimension 4': (['--task-dim', '4'], "argument --task-dim: invalid choice: '4'"),
    'bound not a number': (['--input-lower', 'zero', '--input-upper', '2'],
                           "argument --input-lower: invalid float value: 'zero'"),
}


@pytest.mark.parametrize('case', list(BAD_ARGS))
def test_bad_shape_arguments_exit_2_naming_them_and_write_nothing(case, one_input_bags, tmp_path,
                                                                  capsys):
    args, match = BAD_ARGS[case]
    train_bag, val_bag = one_input_bags
    out = tmp_path / 'out'
    with pytest.raises(SystemExit) as exc:
        train_tool.main(['--bag', str(train_bag), '--val-bag', str(val_bag), '--out', str(out),
                         '--epochs', '1', '--rollout-epochs', '0', *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert re.search(match, err), err
    assert 'Traceback' not in err
    assert not out.exists() and not list(tmp_path.glob('.out.partial-*'))


@pytest.mark.parametrize('args', [['--task-dim', '3'], ['--input-lower', '0', '--input-upper',
                                                       '1']])
def test_shape_arguments_apply_to_bags_only(args, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        train_tool.main(['--data', str(tmp_path), '--out', str(tmp_path / 'out'), *args])
    assert exc.value.code == 2
    assert 'apply to --bag only' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_bounds_that_cannot_be_used_are_shape_errors():
    with pytest.raises(ShapeError, match='the finger has 1 input'):
        InputBounds.parse([0.0, 0.0], [1.0, 1.0], 1, '--input-lower/--input-upper')


def test_recorded_bounds_hold_zero_and_refuse_an_input_never_commanded(tmp_path):
    """Commands of 0.5 … 2 (no settle phase) give [0, 2]: the rest input 0 is inside; an input
    that was 0 throughout is refused by name."""
    stamps = np.arange(1500) * MS
    tips = np.zeros((1500, 1, 3))
    tips[:, 0, 0] = 1e-3 * np.sin(np.linspace(0, 9, 1500))
    u = np.stack([0.5 + 1.5 * np.linspace(0, 1, 1500), np.zeros(1500)], axis=1)
    bag = write_bag(tmp_path / 'b', {'/tip_positions': tips_messages(stamps, tips),
                                     '/torque_commands': _commands(stamps, u)})
    rec = read_recording(bag)
    with pytest.raises(BagDataError, match=r'input ax1 was 0 in every command of .*b: nothing'):
        recorded_bounds([rec])
    one = read_recording(write_bag(tmp_path / 'one', {
        '/tip_positions': tips_messages(stamps, tips),
        '/torque_commands': _commands(stamps, u[:, :1])}))
    bounds = recorded_bounds([one])
    assert bounds.lower[0] == 0.0 and bounds.upper[0] == 2.0 and np.all(bounds.rest == 0.0)


def test_a_moving_z_learned_in_2d_by_default_says_so(tmp_path, capsys):
    sets = [load_bags([shape_bag(tmp_path / name, d=3, m=1, seed=seed)], 'tip_positions',
                      'torque_commands', 1.0, None) for seed, name in enumerate(('t', 'v'))]
    shape, _ = finger_shape(*sets)
    assert shape == FingerShape(2, 1)
    assert "note: the tips' z moves in 1 training bag(s)" in capsys.readouterr().out
    assert finger_shape(*sets, task_dim='auto')[0] == FingerShape(3, 1)
    assert capsys.readouterr().out == ''


def test_the_train_tool_learns_a_one_input_3d_finger_from_bags(tmp_path, capsys):
    """README's command on bags of a (3, 1) finger with --task-dim auto: model.pt of that shape
    with the recorded bounds [0, 2]."""
    train_bag = shape_bag(tmp_path / 'train', d=3, m=1, seed=0)
    val_bag = shape_bag(tmp_path / 'val', d=3, m=1, seconds=2.5, seed=1)
    out = tmp_path / 'out'
    status = train_tool.main(['--bag', str(train_bag), '--val-bag', str(val_bag), '--out',
                              str(out), '--task-dim', 'auto', '--epochs', '20',
                              '--rollout-epochs', '0', '--jerk-psd', '1e4'])
    assert status == (0 if (out / 'params.yaml').is_file() else train_tool.NOT_FIT)
    model = SDCModel(out / 'model.pt')
    assert model.shape == FingerShape(3, 1)
    assert model.input_bounds.lower[0] == 0.0 and 1.9 < model.input_bounds.upper[0] <= 2.0
    assert 'finger shape: 1 input(s)' in capsys.readouterr().out


def test_hand_bags_train_the_hands_shape_with_the_given_bounds(tmp_path, capsys):
    """Bags of two-torque fingers with a planar tip: a (2, 2) model whose checkpoint records the
    bounds given on the command line."""
    from bag_writing import excitation_bag
    train_bag = excitation_bag(tmp_path / 'train', seconds=2.0)
    val_bag = excitation_bag(tmp_path / 'val', seconds=1.5)
    out = tmp_path / 'out'
    status = train_tool.main(['--bag', str(train_bag), '--val-bag', str(val_bag), '--out',
                              str(out), '--epochs', '2', '--rollout-epochs', '0', '--jerk-psd',
                              '1e4', '--meas-std', '1e-6', '--input-lower', '-0.05', '-0.03',
                              '--input-upper', '0.05', '0.03'])
    assert status == (0 if (out / 'params.yaml').is_file() else train_tool.NOT_FIT)
    model = SDCModel(out / 'model.pt')
    assert model.shape == HAND_SHAPE
    assert model.input_bounds == InputBounds([-0.05, -0.03], [0.05, 0.03])
    assert model.data['input_bounds'] == {'lower': [-0.05, -0.03], 'upper': [0.05, 0.03]}
    printed = capsys.readouterr().out
    assert 'finger shape: 2 input(s) (ax0 [-0.05, 0.05], ax1 [-0.03, 0.03]), a tip of 2' in printed
    assert "z moves" not in printed


# -- the Koopman baseline's model for other shapes ---------------------------------------------

def _koopman_records(d: int, m: int, n: int = 3000, seed: int = 0):
    """(pos, vel, u) of the known system of shape (d, m), exact semi-implicit Euler at 1 kHz."""
    G2, bounds = SYSTEMS[(d, m)]
    rng = np.random.default_rng(seed)
    u = np.repeat(bounds.lower + 2 * bounds.half_span * rng.random((n // 25, m)), 25, axis=0)
    p, v = np.zeros((n, d)), np.zeros((n, d))
    for k in range(n - 1):
        v[k + 1] = v[k] + 1e-3 * (-STIFFNESS * p[k] - DAMPING * v[k] + G2 @ u[k])
        p[k + 1] = p[k] + 1e-3 * v[k + 1]
    return p, v, u


@pytest.mark.parametrize('d, m', [(3, 3), (2, 1)])
def test_the_koopman_model_fits_and_round_trips_any_shape(d, m, tmp_path):
    from soft_gripper_sdre.learning.koopman import KoopmanModel, KoopmanSettings, fit_koopman
    p, v, u = _koopman_records(d, m)
    model = fit_koopman([(p, v, u)], np.zeros(3), 1e-3, KoopmanSettings(delays=(2,), degree=2))
    n_s = 2 * d
    assert (model.d, model.m) == (d, m) and model.B.shape == (model.n_z, m)
    assert model.n_z == n_s + d + n_s * (n_s + 1) // 2 and model.C.shape == (n_s, model.n_z)
    acc = model.predict_acceleration(p[:-1], v[:-1], u[:-1])
    true = (v[1:] - v[:-1]) / 1e-3
    assert acc.shape == (len(p) - 1, d)
    assert np.sqrt(np.mean((acc - true) ** 2)) < 0.05 * np.sqrt(np.mean(true ** 2))
    again = KoopmanModel.load(model.save(tmp_path / 'k.npz'))
    np.testing.assert_array_equal(again.B, model.B)
    assert (again.d, again.m) == (d, m)


def test_the_koopman_model_refuses_shapes_it_cannot_take():
    from soft_gripper_sdre.learning.koopman import KoopmanModel, KoopmanSettings, fit_koopman
    s = KoopmanSettings(degree=1)
    with pytest.raises(ValueError, match=r'state_scale must be 2d positive numbers .* \(4 or 6\)'):
        KoopmanModel(np.eye(5), np.zeros((5, 1)), np.ones(5), np.zeros(3), 1e-3, s)
    with pytest.raises(ValueError, match=r'B \(6, m\), m = 1 to 4 inputs'):
        KoopmanModel(np.eye(6), np.zeros((6, 5)), np.ones(6), np.zeros(3), 1e-3, s)
    p, v, u = _koopman_records(2, 1, n=500)
    with pytest.raises(ValueError, match=r'record 1: pos and vel must each be \(N, d\)'):
        fit_koopman([(p, v, u), (p, v, np.hstack([u, u]))], np.zeros(3), 1e-3, s)
    with pytest.raises(ValueError, match=r'record 0: .*got \(500, 4\)'):
        fit_koopman([(np.hstack([p, p]), np.hstack([v, v]), u)], np.zeros(3), 1e-3, s)


# -- the parameter file of a finger of another shape -------------------------------------------

def _derivation():
    """Settings and a checked move as loop_settings.derive returns them for a fit model."""
    from soft_gripper_sdre.analysis.data_facts import DataFacts
    from soft_gripper_sdre.analysis.loop_settings import Derivation, LoopSettings
    settings = LoopSettings(control_period=0.005, meas_std=1e-5, accel_psd=10.0, q_pos=1e6,
                            q_vel=1.0, r=1.0, torque_limit=0.05, torque_lowpass_hz=40.0,
                            integral_gain=5.0, integral_band=1e-3, pd_kp=100.0, pd_kd=1.0,
                            bandwidth_hz=4.0)
    facts = DataFacts(period=0.005, noise_std=1e-5, travel=0.01, torque_limit=0.05,
                      accel_psd_ml=10.0)
    return Derivation(settings, {}, [], facts)


def _declared(node: str) -> dict:
    """The parameters the node declares, as its parameters-file check takes them."""
    import importlib

    from soft_gripper_sdre.nodes.params import declared_types
    return declared_types(importlib.import_module(f'soft_gripper_sdre.nodes.{node}').PARAMS)


@pytest.mark.parametrize('facts, extra', [
    ({}, {}),
    ({'axis': (0.0, 0.6, -0.8), 'bounds': InputBounds([0.0] * 3, [2.0] * 3)},
     {'estimator': {'task_dim': 3},
      'trajectory': {'task_dim': 3, 'direction': [0.0, 0.6, -0.8], 'close_distance': 0.01},
      'controller': {'input_lower': [0.0] * 3, 'input_upper': [2.0] * 3}}),
    ({'bounds': InputBounds([0.0], [2e5]), 'path': ((0.0, 0.0), (1e-3, 2e-3), (1e-3, 5e-3))},
     {'estimator': {'task_dim': 2},
      'trajectory': {'task_dim': 2, 'close_path': [1e-3, 2e-3, 1e-3, 5e-3]},
      'controller': {'input_lower': [0.0], 'input_upper': [2e5]}}),
])
def test_the_parameter_file_carries_the_shape_the_nodes_take(facts, extra, tmp_path):
    """A 3-D move: task_dim 3 for the estimator and the trajectory node, and its direction;
    one-sided inputs: the controller's input_lower/input_upper in place of torque_limit; a curved
    move: the trajectory node's close_path. The hand's file (no bounds, a planar straight move)
    is as it always was. Every node takes its section as declared."""
    from dataclasses import replace

    import yaml

    from soft_gripper_sdre.nodes.params_files import file_problems
    from soft_gripper_sdre.tools.learning.train_bags import params_yaml
    derived = _derivation()
    derived = replace(derived, facts=replace(derived.facts, **facts))
    text = params_yaml(derived, tmp_path / 'model.pt', ['finger_0'], 'bags')
    doc = {key.rsplit('/', 1)[-1]: v['ros__parameters'] for key, v in yaml.safe_load(text).items()}
    for node in ('estimator', 'controller', 'trajectory'):
        for key, value in extra.get(node, {}).items():
            assert doc[node][key] == pytest.approx(value), (node, key)
        path = tmp_path / 'params.yaml'
        path.write_text(text)
        assert file_problems(f'/{node}', _declared(node), str(path)) == [], node
    if 'controller' in extra:
        from soft_gripper_sdre.nodes.params import numbers
        got = InputBounds.parse(numbers(doc['controller']['input_lower'], 'input_lower'),
                                numbers(doc['controller']['input_upper'], 'input_upper'),
                                facts['bounds'].m)
        assert got == facts['bounds'] and 'torque_limit' not in doc['controller']
    if not extra:
        # the hand's shape: the straight move and the plan's fingers and times, no shape keys
        assert {'close_distance', 'side_distance', 'contact_distance'} <= set(doc['trajectory'])
        assert not {'task_dim', 'direction', 'close_path'} & set(doc['trajectory'])
        assert 'task_dim' not in doc['estimator'] and 'input_lower' not in doc['controller']
