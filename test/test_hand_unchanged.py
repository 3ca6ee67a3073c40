"""The hand does not move: the default model's laws give the torques recorded for them on the
hand's closed loop (test/data/hand_law_steps.npz: each step's law inputs and torques over the first
0.6-1.5 s of the grasp with 0.05 mm noise), to 1e-9 N·m, whatever the shape-generic code around
them does."""
from pathlib import Path

import numpy as np
import pytest

from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.learning.model import SDCModel

FIXTURE = Path(__file__).with_name('data') / 'hand_law_steps.npz'
LAWS = ('sdre_ff', 'sdre', 'computed_torque', 'pd', 'lqr')


@pytest.fixture(scope='module')
def recorded():
    return dict(np.load(FIXTURE))


@pytest.mark.parametrize('name', LAWS)
def test_hand_torques_as_recorded(recorded, name):
    law = make_law(name, SDCModel(), Weights(**DEFAULT_WEIGHTS), 0.0625, dt=1e-3)
    inputs = [recorded[f'{name}/{key}'] for key in ('pos', 'vel', 'ref_pos', 'ref_vel', 'ref_acc')]
    expected = recorded[f'{name}/u']
    got = np.stack([law.compute(*(a[k] for a in inputs)).u.copy() for k in range(len(expected))])
    assert got.shape == expected.shape == (len(expected), 4, 2)
    assert np.abs(expected).max() > 1e-3          # the recording moved the fingers
    np.testing.assert_allclose(got, expected, rtol=0.0, atol=1e-9)
