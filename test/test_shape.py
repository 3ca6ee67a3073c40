"""The finger's shape and input bounds as values (sim/shape.py)."""
import numpy as np
import pytest

from soft_gripper_sdre.sim.shape import (
    HAND_SHAPE,
    FingerShape,
    InputBounds,
    ShapeError,
    shape_from_record,
)


def test_hand_shape_is_planar_two_inputs():
    assert (HAND_SHAPE.d, HAND_SHAPE.m, HAND_SHAPE.n_state) == (2, 2, 4)
    assert HAND_SHAPE.network_outputs == (8, 4)
    assert HAND_SHAPE.input_names('finger_0') == ['finger_0/ax0', 'finger_0/ax1']
    assert shape_from_record(None) == HAND_SHAPE


@pytest.mark.parametrize('d, m', [(2, 1), (2, 4), (3, 3), (3, 1)])
def test_shapes_in_range(d, m):
    s = FingerShape(d, m)
    assert s.network_outputs == (2 * d * d, d * m)
    assert len(s.input_names('f')) == m and s.axes == ('X', 'Y', 'Z')[:d]
    assert shape_from_record(s.to_record()) == s


@pytest.mark.parametrize('d, m, named', [(1, 2, 'task dimension'), (4, 2, 'task dimension'),
                                         (2, 0, 'number of inputs'), (3, 5, 'number of inputs'),
                                         (2.5, 2, 'whole number'), (True, 2, 'whole number'),
                                         ('2', 2, 'whole number')])
def test_bad_shapes_are_refused_naming_them(d, m, named):
    with pytest.raises(ShapeError, match=named):
        FingerShape(d, m)


def test_bad_shape_record_names_the_record():
    with pytest.raises(ShapeError, match='checkpoint shape'):
        shape_from_record({'d': 2}, 'checkpoint shape')
    with pytest.raises(ShapeError, match='checkpoint shape: the number of inputs'):
        shape_from_record({'d': 2, 'm': 9}, 'checkpoint shape')


def test_bounds_one_sided_and_symmetric():
    chamber = InputBounds([0.0], [2e5])
    assert chamber.one_sided.tolist() == [True] and chamber.symmetric_limit is None
    assert chamber.rest.tolist() == [0.0] and chamber.mid.tolist() == [1e5]
    motor = InputBounds.symmetric(0.0625, 2)
    assert motor.symmetric_limit == 0.0625 and not motor.one_sided.any()
    u = np.array([[0.1, -0.1], [0.01, 0.02]])
    assert motor.clip(u).tolist() == [[0.0625, -0.0625], [0.01, 0.02]]
    assert motor.saturated(u).tolist() == [[True, True], [False, False]]
    assert InputBounds.from_record(motor.to_record()) == motor
    mixed = InputBounds([0.0, -1.0, 0.2], [3.0, 1.0, 0.5])
    assert mixed.rest.tolist() == [0.0, 0.0, 0.2]


@pytest.mark.parametrize('lower, upper, named', [
    ([0.0], [0.0], 'ax0: the lower bound must be below'),
    ([0.0, 1.0], [1.0, 0.5], 'ax1: the lower bound'),
    ([0.0], [np.inf], 'ax0: bounds must be finite'),
    ([0.0, 0.0], [1.0], '2 lower and 1 upper'),
    ([0.0] * 5, [1.0] * 5, '5 inputs')])
def test_bad_bounds_are_refused_naming_the_input(lower, upper, named):
    with pytest.raises(ShapeError, match=named):
        InputBounds(lower, upper)


def test_parse_checks_against_the_shape():
    with pytest.raises(ShapeError, match='u_lower/u_upper: the finger has 3 input'):
        InputBounds.parse([0.0], [1.0], 3, 'u_lower/u_upper')
    with pytest.raises(ShapeError, match='u_lower/u_upper'):
        InputBounds.parse(['a'], [1.0], 1, 'u_lower/u_upper')
    with pytest.raises(ShapeError, match='the input limit'):
        InputBounds.symmetric(-1.0)
