"""The foreign fingers unlike the hand (soft_gripper_sdre/sim/plants/pneumatic.py,
trunk.py, presets.py): the one-chamber pneumatic finger (one one-sided input, a
pressure lag) and the three-tendon segment (a 3-D tip, three pull-only inputs): rest, energy,
bounds, lag, the trunk's kinematics and static gain, long random inputs, and bad values (no
ROS)."""
import dataclasses
import math

import numpy as np
import pytest

from soft_gripper_sdre.sim.plants.chain import FingerPlant, FingerState, plant_pair
from soft_gripper_sdre.sim.plants.chain_params import PLANTS, FingerParams
from soft_gripper_sdre.sim.plants.pneumatic import P_MAX, PNEUMATIC
from soft_gripper_sdre.sim.plants.presets import (
    GRIPPERS,
    RATES,
    gripper_bounds,
    gripper_shape,
    make_plant,
)
from soft_gripper_sdre.sim.plants.trunk import (
    TRUNKS,
    TrunkParams,
    TrunkPlant,
    TrunkState,
    configuration,
    configuration_jacobian,
    frictionless,
    tip_of,
)
from soft_gripper_sdre.sim.shape import FingerShape, InputBounds

UM = 1e-6


def _pneumatic_frictionless(params: FingerParams, undamped: bool = False) -> FingerParams:
    zeros = (0.0,) * params.n
    extra = dict(damping=zeros) if undamped else {}
    return dataclasses.replace(params, coulomb=zeros, presliding=zeros, **extra)


# -- the presets -----------------------------------------------------------------------------

def test_every_gripper_knows_its_shape_bounds_and_rate():
    expected = {'tendon3': (FingerShape(2, 2), InputBounds.symmetric(0.02, 2)),
                'stiff2': (FingerShape(2, 2), InputBounds.symmetric(0.25, 2)),
                'pneumatic1': (FingerShape(2, 1), InputBounds([0.0], [P_MAX])),
                'trunk3': (FingerShape(3, 3), InputBounds(np.zeros(3), np.full(3, 4.0))),
                'flexor2': (FingerShape(2, 2), InputBounds(np.zeros(2), np.full(2, 4.0)))}
    assert set(GRIPPERS) == set(expected) == set(RATES)
    for kind, (shape, bounds) in expected.items():
        assert gripper_shape(kind) == shape and gripper_bounds(kind) == bounds, kind
        fingers = plant_pair(kind)
        assert len(fingers) == 2 and [f.params.name for f in fingers] == list(GRIPPERS[kind])
        for f in fingers:
            assert f.shape == shape and f.bounds == bounds
            assert f.tip().shape == (shape.d,) and np.all(np.isfinite(f.tip()))
    assert RATES['pneumatic1'] == 100.0 and 200.0 <= RATES['trunk3'] <= 500.0
    assert gripper_bounds('pneumatic1').one_sided.all() and gripper_bounds('trunk3').one_sided.all()


def test_unknown_grippers_and_presets_are_refused_naming_them():
    with pytest.raises(ValueError, match="unknown plant kind 'trunk9'.*pneumatic1, trunk3"):
        plant_pair('trunk9')
    with pytest.raises(ValueError, match="unknown plant kind 'somo'"):
        gripper_shape('somo')
    with pytest.raises(ValueError, match="unknown finger preset 'trunk3_z'"):
        make_plant('trunk3_z')


# -- the pneumatic finger --------------------------------------------------------------------

@pytest.mark.parametrize('name', PNEUMATIC)
def test_the_vented_finger_rests_and_springs_back(name):
    plant = FingerPlant(PNEUMATIC[name]())
    assert plant.m == 1 and plant.state.a.tolist() == [0.0]
    for _ in range(20):
        plant.step((0.0,), 0.05)
        assert np.max(np.abs(plant.tip() - plant.rest_tip)) < 1 * UM
    plant.step((P_MAX,), 1.0)
    assert np.linalg.norm(plant.tip() - plant.rest_tip) > 10e-3
    plant.step((0.0,), 4.0)                      # vented: the springs bring it back (friction:
    assert np.linalg.norm(plant.tip() - plant.rest_tip) < 0.5e-3     # a small offset at most)


@pytest.mark.parametrize('name', PNEUMATIC)
def test_the_pressure_lags_the_command_by_its_time_constant(name):
    params = PNEUMATIC[name]()
    plant = FingerPlant(params)
    tau = params.input_lag
    assert 0.02 <= tau <= 0.1
    plant.step((P_MAX,), tau)
    assert plant.state.a[0] == pytest.approx(P_MAX * (1 - math.exp(-1)), rel=1e-6)
    plant.step((P_MAX,), 2 * tau)
    assert plant.state.a[0] == pytest.approx(P_MAX * (1 - math.exp(-3)), rel=1e-6)
    plant.step((0.0,), tau)                      # vent: it decays with the same lag
    assert plant.state.a[0] == pytest.approx(P_MAX * (1 - math.exp(-3)) * math.exp(-1), rel=1e-6)


@pytest.mark.parametrize('name', PNEUMATIC)
def test_pressure_bends_the_finger_toward_the_palm_and_a_negative_command_is_vented(name):
    plant = FingerPlant(PNEUMATIC[name]())
    gain = plant.static_gain()
    assert gain.shape == (2, 1) and gain[1, 0] > 0
    held = FingerPlant(_pneumatic_frictionless(PNEUMATIC[name]()))
    held.step((0.2 * P_MAX,), 3.0)
    move = held.tip() - held.rest_tip
    assert np.linalg.norm(move) == pytest.approx(0.2 * P_MAX * np.linalg.norm(gain), rel=0.05)
    assert move @ gain[:, 0] / np.linalg.norm(move) / np.linalg.norm(gain) > math.cos(
        math.radians(3))
    vented, sucked = FingerPlant(PNEUMATIC[name]()), FingerPlant(PNEUMATIC[name]())
    for plant in (vented, sucked):
        plant.step((0.3 * P_MAX,), 0.3)
    vented.step((0.0,), 0.3)
    sucked.step((-5 * P_MAX,), 0.3)              # below the bound: clipped to 0 (vented)
    np.testing.assert_array_equal(vented.tip(), sucked.tip())
    over, at_max = FingerPlant(PNEUMATIC[name]()), FingerPlant(PNEUMATIC[name]())
    over.step((3 * P_MAX,), 0.3)
    at_max.step((P_MAX,), 0.3)
    np.testing.assert_array_equal(over.tip(), at_max.tip())


@pytest.mark.parametrize('name', PNEUMATIC)
def test_energy_only_falls_while_vented(name):
    plant = FingerPlant(PNEUMATIC[name]())
    plant.state = FingerState(plant.rest_q + 0.1, np.full(plant.n, 2.0), np.zeros(plant.n),
                              a=np.zeros(1))
    energies = [plant.energy()]
    for _ in range(100):
        plant.step((0.0,), 0.005)
        energies.append(plant.energy())
    assert np.all(np.diff(energies) <= 1e-12 * energies[0])
    rest = FingerPlant(PNEUMATIC[name]()).energy()
    assert energies[-1] - rest < 0.5 * (energies[0] - rest)


def test_the_pneumatic_finger_is_slow_and_well_resolved_at_100_hz():
    """First modes of a few hertz (a 100 Hz loop sees them), the step converged: halving the RK4
    step moves the tip after a second of random pressures by under a micrometre."""
    for name in PNEUMATIC:
        freqs, zeta = FingerPlant(PNEUMATIC[name]()).modes()
        assert 2.0 < freqs[0] < 8.0 and 0.05 < zeta[0] < 0.4, (name, freqs, zeta)
    params = PNEUMATIC['pneumatic1_a']()
    tips = []
    for substep in (params.substep, params.substep / 2):
        plant = FingerPlant(dataclasses.replace(params, substep=substep))
        rng = np.random.default_rng(5)
        for _ in range(100):
            plant.step((rng.uniform(0, P_MAX),), 0.01)
        tips.append(plant.tip())
    assert np.max(np.abs(tips[0] - tips[1])) < 1 * UM


@pytest.mark.parametrize('change, message', [
    (dict(lower_limits=(0.0, 0.0)), 'lower_limits must hold one finite bound per input'),
    (dict(lower_limits=(P_MAX,)), 'each below torque_limit'),
    (dict(lower_limits=(float('nan'),)), 'lower_limits'),
    (dict(input_lag=-0.01), 'input_lag must be finite and >= 0'),
    (dict(input_lag=1e-4), 'input_lag 0.0001 s is too short'),
    (dict(transmission=()), 'transmission must be m × 3 with m = 1 to 4'),
    (dict(transmission=((1e-7, 1e-7, 1e-7),) * 5), 'transmission must be m × 3'),
])
def test_bad_finger_parameters_are_refused_naming_them(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(PNEUMATIC['pneumatic1_a'](), **change)


def test_a_command_of_the_wrong_size_is_refused():
    plant = FingerPlant(PNEUMATIC['pneumatic1_a']())
    with pytest.raises(ValueError, match=r'u must be 1 finite input\(s\)'):
        plant.step((0.0, 0.0), 0.01)
    with pytest.raises(ValueError, match='finite'):
        plant.step((np.inf,), 0.01)
    with pytest.raises(ValueError, match='two finite torques'):     # the hand's fingers: 2
        FingerPlant(PLANTS['stiff2_a']()).step((0.0,), 0.01)


# -- the three-tendon segment ----------------------------------------------------------------

def test_the_constant_curvature_kinematics_invert_and_differentiate():
    """tip_of ∘ configuration is the identity; J = ∂q/∂p matches central differences, on both
    sides of the series near the straight segment."""
    rng = np.random.default_rng(1)
    tips = [np.array([0.12, 0.0, 0.0]), np.array([0.11, 1e-6, -2e-6]),
            np.array([0.1, 5e-4, 8e-4])]
    tips += [np.array([rng.uniform(0.06, 0.13), *rng.uniform(-0.05, 0.05, 2)]) for _ in range(20)]
    for p in tips:
        np.testing.assert_allclose(tip_of(configuration(p)), p, atol=1e-15)
        numeric = np.array([(configuration(p + 1e-7 * e) - configuration(p - 1e-7 * e)) / 2e-7
                            for e in np.eye(3)]).T
        np.testing.assert_allclose(configuration_jacobian(p), numeric, atol=1e-6, rtol=1e-6)
    q = configuration(np.array([0.1, 0.02, 0.01]))
    assert q[2] > 0.1 and np.hypot(q[0], q[1]) > 0          # the arc is longer than the chord


@pytest.mark.parametrize('name', TRUNKS)
def test_the_segment_rests_hanging_straight_and_stays(name):
    params = TRUNKS[name]()
    plant = TrunkPlant(params)
    sag = params.tip_mass * params.gravity / params.axial_stiffness
    np.testing.assert_allclose(plant.rest_tip, [params.length + sag, 0.0, 0.0], atol=1e-12)
    plant.step((2.0, 0.0, 1.0), 0.3)
    plant.reset()
    for _ in range(20):
        plant.step((0.0, 0.0, 0.0), 0.05)
        assert np.max(np.abs(plant.tip() - plant.rest_tip)) < 1 * UM


@pytest.mark.parametrize('name', TRUNKS)
def test_three_tendons_move_the_tip_in_three_independent_directions(name):
    """The static gain 3 × 3 has full rank (its smallest singular value is a fifth of its
    largest or more); each tendon alone bends the tip toward its own side (+ the axis)."""
    params = TRUNKS[name]()
    plant = TrunkPlant(params)
    gain = plant.static_gain()
    assert gain.shape == (3, 3) and np.linalg.matrix_rank(gain) == 3
    sv = np.linalg.svd(gain, compute_uv=False)
    assert sv[-1] / sv[0] > 0.2
    for i, angle in enumerate(params.tendon_angles):
        side = np.array([math.cos(angle), math.sin(angle)])
        lateral = gain[1:, i]
        assert lateral @ side > 0.99 * np.linalg.norm(lateral), i
        assert gain[0, i] < 0, 'pulling shortens the segment'
    held = TrunkPlant(frictionless(params))
    for i in range(3):
        held.reset()
        u = 0.1 * params.tension_limit * np.eye(3)[i]
        held.step(u, 4.0)
        move = held.tip() - held.rest_tip
        np.testing.assert_allclose(move, gain @ u, rtol=0.05, atol=0.02 * np.linalg.norm(move))
        np.testing.assert_allclose(held.tip(), held.equilibrium(u), atol=2 * UM)


@pytest.mark.parametrize('name', TRUNKS)
def test_energy_only_falls_without_tension(name):
    plant = TrunkPlant(TRUNKS[name]())
    plant.state = TrunkState(plant.rest_tip + [-0.01, 0.02, -0.015], np.array([0.1, -0.3, 0.2]),
                             np.zeros(3))
    energies = [plant.energy()]
    for _ in range(200):
        plant.step((0.0, 0.0, 0.0), 0.004)
        energies.append(plant.energy())
    swing = energies[0] - TrunkPlant(TRUNKS[name]()).energy()
    assert np.all(np.diff(energies) <= 1e-9 * swing)
    assert energies[-1] - TrunkPlant(TRUNKS[name]()).energy() < 0.3 * swing


def test_without_damping_or_friction_the_segments_energy_is_conserved():
    """The equations are those of the energy: RK4 drift below 1e-5 of the swing, 16× less
    (RK4's order, with margin) at half the step; a wrong Jacobian term would not do this."""
    params = dataclasses.replace(frictionless(TRUNKS['trunk3_a']()), bending_damping=0.0,
                                 axial_damping=0.0)
    drift = []
    for substep in (params.substep, params.substep / 2):
        plant = TrunkPlant(dataclasses.replace(params, substep=substep))
        rest = plant.energy()
        plant.state = TrunkState(plant.rest_tip + [-0.005, 0.02, 0.01], np.array([0.0, 0.2, -0.1]),
                                 np.zeros(3))
        e0 = plant.energy()
        worst = 0.0
        for _ in range(30):
            plant.step((0.0, 0.0, 0.0), 0.01)
            worst = max(worst, abs(plant.energy() - e0))
        drift.append(worst / (e0 - rest))
    assert drift[0] < 1e-5
    assert drift[1] < drift[0] / 12


def test_tensions_are_pull_only_and_clipped():
    params = TRUNKS['trunk3_a']()
    pushed, slack = TrunkPlant(params), TrunkPlant(params)
    pushed.step((-3.0, 0.0, -1.0), 0.2)
    slack.step((0.0, 0.0, 0.0), 0.2)
    np.testing.assert_array_equal(pushed.tip(), slack.tip())
    over, at_max = TrunkPlant(params), TrunkPlant(params)
    over.step((40.0, 0.0, 9.0), 0.2)
    at_max.step((4.0, 0.0, 4.0), 0.2)
    np.testing.assert_array_equal(over.tip(), at_max.tip())
    with pytest.raises(ValueError, match='three finite numbers'):
        over.step((1.0, 1.0), 0.01)
    with pytest.raises(ValueError, match='three finite numbers'):
        over.step((1.0, np.nan, 1.0), 0.01)
    with pytest.raises(ValueError, match='dt'):
        over.step((1.0, 1.0, 1.0), -0.1)


@pytest.mark.parametrize('kind', ['pneumatic1', 'trunk3'])
def test_long_random_bounded_inputs_keep_the_tips_finite_and_in_reach(kind):
    """10 s of random inputs held 2 to 50 ms, a quarter of them far outside the bounds (clipped):
    the tips stay finite and within the finger's length of the base; with the lag the delivered
    pressure never leaves [0, p_max]."""
    rng = np.random.default_rng(11)
    for plant in plant_pair(kind):
        b = plant.bounds
        reach = (sum(plant.params.lengths) if hasattr(plant.params, 'lengths')
                 else 1.2 * plant.params.length)
        t = 0.0
        while t < 10.0:
            u = rng.uniform(b.lower, b.upper)
            if rng.random() < 0.25:
                u = u + rng.choice([-1, 1], b.m) * 5 * (b.upper - b.lower)
            dt = rng.uniform(0.002, 0.05)
            plant.step(u, dt)
            t += dt
            tip = plant.tip()
            assert np.all(np.isfinite(tip)) and np.linalg.norm(tip) <= reach + 1e-9, (t, tip)
            if getattr(plant.state, 'a', None) is not None:
                assert b.contains(plant.state.a, tol=1e-6), plant.state.a


def test_the_segment_is_served_at_200_to_500_hz_faster_than_real_time():
    import time
    plant = TrunkPlant(TRUNKS['trunk3_a']())
    start = time.perf_counter()
    for k in range(250):                          # one second at 250 Hz
        plant.step((2.0 * (k % 50 < 25), 1.0, 0.5), 0.004)
    assert time.perf_counter() - start < 0.5
    freqs, zeta = plant.modes()
    assert 3.0 < freqs[0] < 8.0 and freqs[2] < 50.0 and 0.05 < zeta[0] < 0.2


@pytest.mark.parametrize('change, message', [
    (dict(tendon_angles=(0.0, 0.0, 0.0)), 'B is singular'),
    (dict(tendon_angles=(0.0, 1.0)), 'tendon_angles must hold three'),
    (dict(tension_limit=0.0), 'tension_limit must be finite and > 0'),
    (dict(length=float('nan')), 'length must be finite and > 0'),
    (dict(axial_damping=-1.0), 'damping must be >= 0'),
    (dict(coulomb=(0.0, 0.05)), 'coulomb and presliding must both be positive'),
    (dict(substep=2e-3), 'too fast for RK4'),
])
def test_bad_segment_parameters_are_refused_naming_them(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(TRUNKS['trunk3_a'](), **change)
    assert isinstance(TRUNKS['trunk3_a'](), TrunkParams)
