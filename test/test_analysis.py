"""Ground truth from the simulator: the input matrix, and the loop around the frictionless
finger."""
import numpy as np
import pytest

from soft_gripper_sdre.analysis.ground_truth import (
    input_matrix_survey,
    linear_finger,
    loop_spectral_radius,
)
from soft_gripper_sdre.analysis.metrics import angle_difference, column_angles
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.learning.model import PAPER_DATA_MODEL, SDCModel

REST = np.zeros((1, 2))


@pytest.fixture(scope='module')
def surveys():
    return {name: input_matrix_survey(SDCModel(path), REST)
            for name, path in (('default', None), ('paper_data', PAPER_DATA_MODEL))}


def test_true_input_matrix_at_rest_pushes_y_with_ax0_and_x_with_ax1(surveys):
    true = surveys['default'].true[0]
    np.testing.assert_allclose(column_angles(true), [-90.0, 0.0], atol=0.5)   # +ax0 → −Y, +ax1 → +X


def test_identifying_excitation_recovers_the_g2_column_directions(surveys):
    """The shipped model's G2 columns lie within 10° of J M⁻¹ B's at rest; the same preset
    trained on the paper's equal-torque signals cannot tell the columns apart."""
    assert np.all(surveys['default'].angle_error[0] < 10.0), surveys['default'].angle_error
    assert np.all(surveys['paper_data'].angle_error[0] > 20.0), surveys['paper_data'].angle_error


def test_angle_difference_wraps():
    assert angle_difference(179.0, -179.0) == pytest.approx(2.0)
    assert angle_difference(-90.0, 90.0) == pytest.approx(180.0)


def test_frictionless_loop_grows_faster_with_position_weight():
    """Around the linearised finger with friction off, the 1 ms loop has a growing mode, and
    it grows faster as q_pos rises: friction is what keeps the real loop stable (README)."""
    plant = linear_finger(1e-3)
    model = SDCModel()
    radii = [loop_spectral_radius(plant, model, Weights(q, 0.0, 1.6e4).Q, Weights(q, 0.0, 1.6e4).R,
                                  1.0, 5e-5)[0] for q in (2.5e5, 1e6, 4e6)]
    assert radii[0] > 1.0
    assert radii[0] < radii[1] < radii[2]
    ad, _, _ = plant
    assert np.abs(np.linalg.eigvals(ad)).max() == pytest.approx(1.0, abs=1e-9)   # undamped alone


def test_torque_roll_off_cuts_the_spillover_growth():
    """The default 40 Hz roll-off slows the growing ~57 Hz mode of the frictionless loop by an
    order of magnitude at the default weights (what lets the loop hold under 0.2 mm noise)."""
    from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, DEFAULT_WEIGHTS
    plant = linear_finger(1e-3)
    model = SDCModel()
    w = Weights(**DEFAULT_WEIGHTS)
    bare, f_bare = loop_spectral_radius(plant, model, w.Q, w.R, 1.0, 5e-5)
    rolled, _ = loop_spectral_radius(plant, model, w.Q, w.R, 1.0, 5e-5,
                                     lowpass_hz=DEFAULT_LOWPASS_HZ)
    assert 50.0 < f_bare < 65.0                      # the finger's fourth bending mode (~59 Hz)
    assert (rolled - 1.0) < 0.2 * (bare - 1.0)


def test_a_long_period_destabilises_the_23_hz_bend_and_the_capped_roll_off_slows_it():
    """At 10 ms the frictionless loop's least stable mode is the finger's ~23 Hz bend (moved to
    ~25–30 Hz by the loop), not the ~59 Hz one of the 1 ms loop. A 40 Hz corner hardly attenuates
    it; the corner capped at a tenth of the sampling rate (10 Hz) halves its growth per second
    (docs/design/control_period.md)."""
    from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, DEFAULT_WEIGHTS
    dt = 1e-2
    plant = linear_finger(dt)
    w = Weights(**DEFAULT_WEIGHTS)
    fixed_40, f_fixed = loop_spectral_radius(plant, SDCModel(), w.Q, w.R, 1.0, 5e-5, dt=dt,
                                             lowpass_hz=DEFAULT_LOWPASS_HZ, capped=False)
    capped, _ = loop_spectral_radius(plant, SDCModel(), w.Q, w.R, 1.0, 5e-5, dt=dt,
                                     lowpass_hz=DEFAULT_LOWPASS_HZ)
    assert 20.0 < f_fixed < 35.0
    assert fixed_40 > 1.0
    assert np.log(capped) < 0.5 * np.log(fixed_40)             # growth per step (and per second)
