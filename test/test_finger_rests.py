"""A model learned from several fingers knows each one's rest, and the controller puts every finger
into the model's frame by it (nodes/tracking_step.rest_shift)."""
import numpy as np

from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.nodes.tracking_step import rest_shift


class TwoFingerModel:
    """The two attributes rest_shift reads, as a checkpoint trained on two fingers gives them."""

    rest_tip = np.array([0.078, 0.044, 0.0])
    finger_rests = {'index': np.array([0.078, 0.044, 0.0]), 'thumb': np.array([0.081, 0.039, 0.0])}


def test_each_finger_is_shifted_by_its_own_rest():
    shift = rest_shift(TwoFingerModel(), ('index', 'thumb'))
    np.testing.assert_allclose(shift, [[0.0, 0.0], [-0.003, 0.005]], atol=1e-15)
    # the thumb at its own rest is at the model's rest once shifted
    np.testing.assert_allclose(TwoFingerModel.finger_rests['thumb'][:2] + shift[1],
                               TwoFingerModel.rest_tip[:2])


def test_no_shift_without_every_finger_or_when_all_rest_alike():
    assert rest_shift(TwoFingerModel(), ('index', 'middle')) is None
    assert rest_shift(TwoFingerModel(), ('index',)) is None


def test_the_shipped_model_of_one_finger_has_no_finger_rests():
    model = SDCModel()
    assert model.finger_rests == {}
    assert rest_shift(model, ('finger_0', 'finger_1')) is None
