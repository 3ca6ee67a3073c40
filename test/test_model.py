"""The SDC model: network shapes, A(x)/G(x) structure, real training, checkpoints and their
refusal."""
from dataclasses import asdict, replace
import json

import numpy as np
import pytest
import torch

from soft_gripper_sdre.learning.model import (
    DEFAULT_MODEL,
    FORMAT_VERSION,
    ModelFileError,
    SDCModel,
    SDCNet,
    read_checkpoint,
)
from soft_gripper_sdre.learning.train_settings import PRESETS
from soft_gripper_sdre.learning.training import (
    TrainResult,
    fingerprint,
    save_checkpoint,
    train,
)
from soft_gripper_sdre.sim.hand import SimConfig
from soft_gripper_sdre.tools.learning.collect import collect_signal

TRAIN_SIGNALS = ('u1', 'u2', 'x1', 'x2')
EPOCHS = 15


def states(name: str, duration: float = 1.0):
    """Translated true state x (N, 4), input u (N, 2) and true acceleration (N, 2) from the sim."""
    r = collect_signal(name, SimConfig(scene='finger'), duration=duration)
    x = np.hstack([r['tip_true'][:, :2] - r['rest_tip'][:2], r['vel_true'][:, :2]])
    return x, r['u'], r['acc_true'][:, :2], r['rest_tip']


@pytest.fixture(scope='module')
def data():
    """1 s each of u1, u2, x1, x2 for training and u4 for validation, from the simulated finger."""
    torch.set_num_threads(1)
    runs = [states(name) for name in TRAIN_SIGNALS]
    x, u, acc = (np.vstack([run[i] for run in runs]) for i in range(3))
    x_val, u_val, acc_val, rest_tip = states('u4')
    return dict(x=x, u=u, acc=acc, x_val=x_val, u_val=u_val, acc_val=acc_val, rest_tip=rest_tip)


def fit(data, **changes):
    settings = replace(PRESETS['default'], **{'epochs': EPOCHS, **changes})
    return train(data['x'], data['u'], data['acc'], data['x_val'], data['u_val'], data['acc_val'],
                 settings), settings


@pytest.fixture(scope='module')
def trained(data):
    """A short real training run of the default preset (15 epochs)."""
    return fit(data)


@pytest.fixture(scope='module')
def checkpoint(trained, data, tmp_path_factory):
    """The trained networks saved as a checkpoint file."""
    result, settings = trained
    path = tmp_path_factory.mktemp('ckpt') / 'model.pt'
    save_checkpoint(path, result, rest_tip=data['rest_tip'], dt=1e-3, settings=settings,
                    data={'train_signals': list(TRAIN_SIGNALS),
                          'fingerprint': fingerprint(data['x'], data['u'], data['acc'])},
                    metrics={'note': 'test run', 'r2': [0.5, 0.9]})
    return path


@pytest.fixture(scope='module')
def model(checkpoint):
    return SDCModel(checkpoint)


def scaled_loss(net, data, scales):
    """Eq. 18 on the validation set in scaled units, as train() computes it."""
    t = lambda a, k: torch.as_tensor(a / scales[k], dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        pred = net.accel(t(data['x_val'], 'x'), t(data['u_val'], 'u'))
        return float(((pred - t(data['acc_val'], 'acc')) ** 2).sum(dim=1).mean())


# ----------------------------------------------------------------------------------------------
# networks and A(x), G(x)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize('hidden', [32, 8])
def test_sdcnet_output_shapes(hidden):
    """[A21 A22] is (B, 2, 4), G2 is (B, 2, 2), the acceleration (B, 2); hidden sets the width."""
    torch.manual_seed(0)
    net = SDCNet(hidden)
    assert net.a_net[0].out_features == hidden and net.g_net[2].in_features == hidden
    xs, us = torch.randn(5, 4), torch.randn(5, 2)
    a, g = net(xs)
    assert a.shape == (5, 2, 4) and g.shape == (5, 2, 2)
    assert net.accel(xs, us).shape == (5, 2)


def test_sdcnet_unstacks_columns():
    """vec stacks columns: output k of NN_θ1 is [A21 A22][k % 2, k // 2], of NN_θ2 is
    G2[k % 2, k // 2]."""
    torch.manual_seed(0)
    net = SDCNet()
    xs = torch.randn(3, 4)
    a, g = net(xs)
    with torch.no_grad():
        a_vec, g_vec = net.a_net(xs), net.g_net(xs)
    for k in range(8):
        torch.testing.assert_close(a[:, k % 2, k // 2], a_vec[:, k])
    for k in range(4):
        torch.testing.assert_close(g[:, k % 2, k // 2], g_vec[:, k])


def test_A_and_G_have_the_companion_structure(model, data):
    """A = [[0, I], [A21, A22]] and G = [[0], [G2]] for one state and for a batch (numpy in and
    out)."""
    x = data['x_val'][::100]
    A, G = model.AG(x)
    assert isinstance(A, np.ndarray) and A.shape == (len(x), 4, 4) and G.shape == (len(x), 4, 2)
    np.testing.assert_array_equal(A[:, :2, :2], 0.0)
    np.testing.assert_array_equal(A[:, :2, 2:], np.broadcast_to(np.eye(2), (len(x), 2, 2)))
    np.testing.assert_array_equal(G[:, :2, :], 0.0)
    assert np.all(np.isfinite(A)) and np.all(np.isfinite(G))
    assert np.ptp(A[:, 2:, :], axis=0).max() > 0, 'A21, A22 must depend on the state'
    A1, G1 = model.AG(x[3])
    assert A1.shape == (1, 4, 4) and G1.shape == (1, 4, 2)
    np.testing.assert_allclose(A1[0], A[3], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(G1[0], G[3], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(model.A(x), A)
    np.testing.assert_array_equal(model.G(x), G)


def test_AG_rejects_a_wrong_state_shape(model):
    with pytest.raises(ValueError, match=r'x must have shape \(4,\) or \(n, 4\)'):
        model.AG(np.zeros((2, 3)))


def test_xdot_is_A_x_plus_G_u(model, data):
    """ẋ = A(x) x + G(x) u; its first two rows are the velocities."""
    x, u = data['x_val'][::50], data['u_val'][::50]
    A, G = model.AG(x)
    xdot = model.xdot(x, u)
    np.testing.assert_allclose(xdot, np.einsum('nij,nj->ni', A, x) + np.einsum('nij,nj->ni', G, u),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(xdot[:, :2], x[:, 2:])
    np.testing.assert_allclose(model.xdot(x[0], u[0])[0], xdot[0], rtol=1e-12, atol=1e-12)


def test_numpy_model_matches_the_torch_network(model, trained, data):
    """SDCModel's physical ẍ equals the torch network's scaled prediction times s_acc."""
    result, _ = trained
    s = result.scales
    x, u = data['x_val'], data['u_val']
    with torch.no_grad():
        scaled = result.net.accel(torch.as_tensor(x / s['x'], dtype=torch.float32),
                                  torch.as_tensor(u / s['u'], dtype=torch.float32)).double().numpy()
    np.testing.assert_allclose(model.xdot(x, u)[:, 2:], scaled * s['acc'], rtol=1e-4,
                               atol=1e-4 * np.abs(data['acc_val']).max())


# ----------------------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------------------

def test_training_lowers_the_validation_loss(trained, data):
    """15 epochs on simulator data cut the u4 validation loss well below the untrained network's,
    and the weights of the best validation epoch are the ones returned."""
    result, settings = trained
    torch.manual_seed(settings.seed)
    untrained = scaled_loss(SDCNet(settings.hidden), data, result.scales)
    assert len(result.val_loss) == len(result.train_loss) == EPOCHS
    assert all(np.isfinite(result.val_loss)) and all(np.isfinite(result.train_loss))
    assert min(result.val_loss) < 0.6 * untrained, (untrained, result.val_loss)
    assert result.val_loss[-1] < result.val_loss[0] and result.train_loss[-1] < result.train_loss[0]
    assert result.val_loss[result.best_epoch] == min(result.val_loss)
    assert scaled_loss(result.net, data, result.scales) == pytest.approx(min(result.val_loss),
                                                                         rel=1e-5)


def test_training_is_deterministic(data):
    """The same seed gives bit-identical weights and losses; another seed gives other weights."""
    (a, _), (b, _), (c, _) = (fit(data, epochs=3, seed=s) for s in (7, 7, 8))
    assert a.val_loss == b.val_loss
    for key, value in a.net.state_dict().items():
        assert torch.equal(value, b.net.state_dict()[key]), key
    assert not all(torch.equal(v, c.net.state_dict()[k]) for k, v in a.net.state_dict().items())


def test_train_rejects_wrong_shapes(data):
    with pytest.raises(ValueError, match=r'u must have shape \(N, 2\)'):
        train(data['x'], data['u'][:, :1], data['acc'], data['x_val'], data['u_val'],
              data['acc_val'], PRESETS['default'])


# ----------------------------------------------------------------------------------------------
# checkpoints
# ----------------------------------------------------------------------------------------------

def test_checkpoint_round_trip(checkpoint, trained, data, model, tmp_path):
    """What save_checkpoint writes reads back unchanged, and a re-saved copy gives identical
    A, G."""
    result, settings = trained
    ckpt = read_checkpoint(checkpoint)
    assert ckpt['format_version'] == FORMAT_VERSION
    assert ckpt['architecture']['hidden'] == settings.hidden
    for key, value in result.net.state_dict().items():
        assert torch.equal(ckpt['state_dict'][key], value), key
    for key, value in result.scales.items():
        np.testing.assert_array_equal(ckpt['scales'][key].numpy(), value)
    np.testing.assert_array_equal(ckpt['rest_tip'].numpy(), data['rest_tip'])
    assert ckpt['dt'] == 1e-3 and ckpt['settings'] == asdict(settings)
    assert ckpt['data']['fingerprint'] == fingerprint(data['x'], data['u'], data['acc'])
    assert ckpt['metrics'] == {'note': 'test run', 'r2': [0.5, 0.9]}
    assert ckpt['history']['val_loss'] == result.val_loss
    assert ckpt['history']['best_epoch'] == result.best_epoch
    # re-save what was read: A(x), G(x) must be bit-identical
    again = TrainResult(ckpt['net'], {k: v.numpy() for k, v in ckpt['scales'].items()})
    copy = save_checkpoint(tmp_path / 'copy.pt', again, rest_tip=ckpt['rest_tip'].numpy(),
                           dt=ckpt['dt'], settings=settings, data=ckpt['data'])
    x = data['x_val'][::37]
    for m1, m2 in zip(model.AG(x), SDCModel(copy).AG(x)):
        np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(model.rest_tip, data['rest_tip'])
    assert model.dt == 1e-3 and model.path == checkpoint


def test_checkpoint_is_plain_data(checkpoint):
    """The file loads with torch.load(weights_only=True), as the design requires."""
    ckpt = torch.load(checkpoint, weights_only=True)
    assert set(ckpt) >= {'format_version', 'architecture', 'state_dict', 'scales', 'rest_tip', 'dt',
                         'settings', 'data', 'metrics', 'history'}


def resave(tmp_path, checkpoint, edit):
    """Load the good checkpoint as plain data, save ``edit(checkpoint)`` as bad.pt."""
    path = tmp_path / 'bad.pt'
    torch.save(edit(torch.load(checkpoint, weights_only=True)), path)
    return path


def without(d, key):
    return {k: v for k, v in d.items() if k != key}


LAYOUT = 'does not match the network layout'
BAD_CHECKPOINTS = {
    'format version': (lambda c: {**c, 'format_version': FORMAT_VERSION + 1},
                       f'format version {FORMAT_VERSION + 1}, this package reads version '
                       f'{FORMAT_VERSION}'),
    'declared hidden size': (lambda c: {**c, 'architecture': {**c['architecture'], 'hidden': 64}},
                             LAYOUT),
    'weights of another size': (lambda c: {**c, 'state_dict': SDCNet(16).state_dict()}, LAYOUT),
    'missing layer': (lambda c: {**c, 'state_dict': without(c['state_dict'], 'g_net.4.bias')},
                      LAYOUT),
    'no architecture': (lambda c: without(c, 'architecture'), LAYOUT),
    'scale shape': (lambda c: {**c, 'scales': {**c['scales'],
                                               'x': torch.ones(3, dtype=torch.float64)}},
                    'scale x has shape'),
    'rest tip shape': (lambda c: {**c, 'rest_tip': torch.zeros(2)}, 'rest_tip has shape'),
    'not a dict': (lambda c: [1, 2, 3], 'is not a soft_gripper_sdre checkpoint'),
    'no history': (lambda c: without(c, 'history'), 'history is missing'),
    'metrics not a mapping': (lambda c: {**c, 'metrics': 'none'}, 'metrics must be a mapping'),
    'period a string': (lambda c: {**c, 'dt': 'abc'}, "dt must be a period > 0 s, got 'abc'"),
    'period zero': (lambda c: {**c, 'dt': 0.0}, 'dt must be a period > 0 s'),
    'rest tip NaN': (lambda c: {**c, 'rest_tip': torch.tensor([float('nan'), 0.0, 0.0])},
                     'rest_tip holds a NaN or an infinity'),
    'scale infinite': (lambda c: {**c, 'scales': {**c['scales'], 'u': c['scales']['u'] * np.inf}},
                       'scale u holds a NaN or an infinity'),
    'weight NaN': (lambda c: {**c, 'state_dict': {**c['state_dict'], 'g_net.4.bias':
                                                  c['state_dict']['g_net.4.bias'] * np.nan}},
                   'weight g_net.4.bias holds a NaN'),
}


@pytest.mark.parametrize('case', list(BAD_CHECKPOINTS))
def test_read_checkpoint_refuses_a_wrong_layout(case, checkpoint, tmp_path):
    """Another format version or network layout is a ModelFileError naming the file and the
    reason."""
    edit, match = BAD_CHECKPOINTS[case]
    path = resave(tmp_path, checkpoint, edit)
    with pytest.raises(ModelFileError, match=match) as exc:
        read_checkpoint(path)
    assert str(path) in str(exc.value)
    with pytest.raises(ModelFileError):
        SDCModel(path)


def test_read_checkpoint_refuses_a_missing_file(tmp_path):
    path = tmp_path / 'nothing.pt'
    with pytest.raises(ModelFileError, match=f'model file {path} does not exist'):
        read_checkpoint(path)


def test_read_checkpoint_refuses_a_truncated_file(checkpoint, tmp_path):
    """Half a checkpoint is refused as unreadable or truncated."""
    path = tmp_path / 'half.pt'
    raw = checkpoint.read_bytes()
    path.write_bytes(raw[:len(raw) // 2])
    with pytest.raises(ModelFileError, match='unreadable or truncated') as exc:
        read_checkpoint(path)
    assert str(path) in str(exc.value)


class _OpensAFile:
    """Unpickling this object calls open(marker, 'w'): a stand-in for arbitrary code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, 'w'))


def test_read_checkpoint_refuses_pickled_objects_without_running_them(checkpoint, tmp_path):
    """A checkpoint carrying a pickled callable is refused and the callable never runs."""
    marker = tmp_path / 'code_ran'
    path = resave(tmp_path, checkpoint, lambda c: {**c, 'extra': _OpensAFile(marker)})
    with pytest.raises(ModelFileError, match='objects other than tensors') as exc:
        read_checkpoint(path)
    assert str(path) in str(exc.value) and '(it needs io.open)' in str(exc.value)
    assert 'Weights only load failed' not in str(exc.value)
    assert not marker.exists(), 'the pickled payload was executed'
    # the payload is live: an unrestricted load does run it
    loaded = torch.load(path, weights_only=False)
    loaded['extra'].close()
    assert marker.exists()


@pytest.mark.parametrize('content', [b'hello world ' * 10, bytes(range(256)) * 4, b''],
                         ids=['text', 'random bytes', 'empty'])
def test_read_checkpoint_says_a_corrupt_file_is_not_a_checkpoint(tmp_path, content):
    """Bytes that are not a torch.save archive are named as such, not as pickled objects."""
    path = tmp_path / 'notes.pt'
    path.write_bytes(content)
    with pytest.raises(ModelFileError) as exc:
        read_checkpoint(path)
    message = str(exc.value)
    assert message.startswith(f'model file {path} is not a checkpoint: a torch.save file is a '
                              'zip archive')
    assert 'pickled' not in message and 'objects other than tensors' not in message


# ----------------------------------------------------------------------------------------------
# the shipped model
# ----------------------------------------------------------------------------------------------

def test_default_model_loads_with_the_expected_input_matrix():
    """The shipped model loads by default; G2(0) matches its JSON: +u_ax1 → +X, +u_ax0 → −Y."""
    model = SDCModel()
    assert model.path == DEFAULT_MODEL and DEFAULT_MODEL.is_file()
    assert model.dt == 1e-3 and model.rest_tip.shape == (3,) and np.all(np.isfinite(model.rest_tip))
    summary = json.loads(DEFAULT_MODEL.with_suffix('.json').read_text())
    G2 = model.G(np.zeros(4))[0, 2:, :]
    np.testing.assert_allclose(G2, summary['G2_at_origin'], rtol=1e-9)
    assert G2[0, 1] > 0 and G2[1, 0] < 0
    assert abs(G2[0, 1]) > 10 * abs(G2[0, 0]) and abs(G2[1, 0]) > 10 * abs(G2[1, 1])
    assert model.metrics['G2_at_origin'] == summary['G2_at_origin']
    np.testing.assert_array_equal(model.xdot(np.zeros(4), np.zeros(2)), 0.0)


@pytest.mark.parametrize('path', [DEFAULT_MODEL, DEFAULT_MODEL.with_name('paper_data.pt')])
def test_fused_numpy_network_equals_the_torch_networks_in_double(path):
    """The fused evaluator (both MLPs side by side, scalings folded in, outputs reordered) gives the
    physical blocks of the torch networks run in float64: A2_ij = s_a,i Â_ij / s_x,j,
    G2_ij = s_a,i Ĝ_ij / s_u,j."""
    ckpt = read_checkpoint(path)
    net = ckpt['net'].double()
    s = {k: v.numpy() for k, v in ckpt['scales'].items()}
    x = np.random.default_rng(0).normal(size=(64, 4)) * [5e-3, 5e-3, 5e-2, 5e-2]
    with torch.no_grad():
        a, g = (t.numpy() for t in net(torch.as_tensor(x / s['x'])))
    A2, G2 = SDCModel(path).sdc_blocks(x)
    np.testing.assert_allclose(A2, a * s['acc'][:, None] / s['x'][None, :], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(G2, g * s['acc'][:, None] / s['u'][None, :], rtol=1e-12, atol=1e-12)
    A, G = SDCModel(path).AG(x)
    np.testing.assert_array_equal(A[:, 2:, :], A2)
    np.testing.assert_array_equal(G[:, 2:, :], G2)
