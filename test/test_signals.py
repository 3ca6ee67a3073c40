"""Excitation signals: eq. 25 of the paper and the identifying multisines."""
import numpy as np
import pytest

from soft_gripper_sdre.sim.signals import SIGNALS, get_signal, signal_names
from soft_gripper_sdre.sim.units import TORQUE_SCALE

T = np.array([0.0, 0.25, 0.5, 1.3, 7.77])


@pytest.mark.parametrize('name, f', [
    ('u1', lambda t: 25 * np.sin(np.pi * t)),
    ('u2', lambda t: 25 * np.sin(0.5 * np.pi * t) + 2),
    ('u3', lambda t: 10 * np.sin(2 * np.pi * t) + 15 * np.sin(np.pi * t)),
    ('u4', lambda t: 6 * np.sin(3 * np.pi * t) + 7 * np.sin(2 * np.pi * t) + 8 * np.sin(np.pi * t)),
])
def test_paper_signals_are_eq25_in_newton_metres(name, f):
    u = get_signal(name)(T)
    assert u.shape == (T.size, 2)
    np.testing.assert_allclose(u[:, 0] * TORQUE_SCALE, f(T))
    np.testing.assert_array_equal(u[:, 0], u[:, 1])


@pytest.mark.parametrize('name', ['x1', 'x2'])
def test_identifying_signals_drive_the_axes_independently(name):
    t = np.arange(0.0, 10.0, 1e-3)
    u = get_signal(name)(t) * TORQUE_SCALE
    assert np.abs(u).max() <= 25.0
    corr = np.corrcoef(u[:, 0], u[:, 1])[0, 1]
    assert abs(corr) < 0.2
    for a in range(2):                          # both signs of each input
        assert u[:, a].min() < -10 and u[:, a].max() > 10


def test_registry_and_unknown_name():
    assert signal_names() == list(SIGNALS) and {'u1', 'u2', 'u3', 'u4'} <= set(SIGNALS)
    with pytest.raises(KeyError, match='known signals'):
        get_signal('u9')
