"""The foreign fingers (soft_gripper_sdre/sim/plants/): rest, energy, conditioning of the
inputs, step-size convergence, friction and speed, on every preset (no ROS)."""
import dataclasses

import numpy as np
import pytest

from soft_gripper_sdre.sim.plants.chain import FingerPlant, FingerState, input_angle, plant_pair
from soft_gripper_sdre.sim.plants.chain_params import PAIRS, PLANTS, FingerParams
from soft_gripper_sdre.sim.shape import InputBounds

UM = 1e-6


def _frictionless(params: FingerParams, undamped: bool = False) -> FingerParams:
    zeros = (0.0,) * params.n
    extra = dict(damping=zeros) if undamped else {}
    return dataclasses.replace(params, coulomb=zeros, presliding=zeros, **extra)


def _free_frequency(plant: FingerPlant, seconds: float, dt: float) -> float:
    """The dominant frequency [Hz] of the tip's Y after release from a deflected equilibrium:
    the peak of the spectrum of the free response (frictionless plants only)."""
    plant.state = FingerState(plant.equilibrium((0.3 * plant.params.torque_limit, 0.0)),
                              np.zeros(plant.n), np.zeros(plant.n))
    y = []
    for _ in range(int(round(seconds / dt))):
        plant.step((0.0, 0.0), dt)
        y.append(plant.tip()[1])
    y = np.asarray(y) - np.mean(y)
    spectrum = np.abs(np.fft.rfft(y * np.hanning(len(y)), n=16 * len(y)))
    return float(np.fft.rfftfreq(16 * len(y), dt)[np.argmax(spectrum)])


@pytest.mark.parametrize('name', PLANTS)
def test_rest_is_an_equilibrium(name):
    plant = FingerPlant(PLANTS[name]())
    plant.step((0.0, 0.5 * plant.params.torque_limit), 0.2)
    plant.reset()
    np.testing.assert_array_equal(plant.tip(), plant.rest_tip)
    for _ in range(40):
        plant.step((0.0, 0.0), 0.05)
        assert np.max(np.abs(plant.tip() - plant.rest_tip)) < 1 * UM
    assert plant.state.t == pytest.approx(2.0)


@pytest.mark.parametrize('name', PLANTS)
def test_energy_only_falls_without_input(name):
    plant = FingerPlant(PLANTS[name]())
    plant.state = FingerState(plant.rest_q + 0.08, np.full(plant.n, 2.0), np.zeros(plant.n))
    energies = [plant.energy()]
    for _ in range(100):
        plant.step((0.0, 0.0), 0.005)
        energies.append(plant.energy())
    assert np.all(np.diff(energies) <= 1e-12 * energies[0])
    rest = FingerPlant(PLANTS[name]()).energy()
    assert energies[-1] - rest < 0.5 * (energies[0] - rest)


@pytest.mark.parametrize('name', ['tendon3_index', 'stiff2_b'])
def test_without_damping_or_friction_energy_is_conserved(name):
    """The equations of motion are those of the energy: without damping and friction E drifts
    by less than 1e-4 of its swing over 0.3 s, and by 16× less (RK4's order) at half the step,
    which a wrong mass-matrix, Coriolis or gravity term would not do."""
    params = _frictionless(PLANTS[name](), undamped=True)
    drift = []
    for substep in (params.substep, params.substep / 2):
        plant = FingerPlant(dataclasses.replace(params, substep=substep))
        swing = -plant.energy()
        plant.state = FingerState(plant.rest_q + 0.1, np.full(plant.n, 1.0), np.zeros(plant.n))
        e0 = plant.energy()
        swing += e0
        worst = 0.0
        for _ in range(30):
            plant.step((0.0, 0.0), 0.01)
            worst = max(worst, abs(plant.energy() - e0))
        drift.append(worst / swing)
    assert drift[0] < 1e-4
    assert drift[1] < drift[0] / 16


@pytest.mark.parametrize('name', [n for n in PLANTS if not n.startswith('flexor2')])
def test_the_two_inputs_move_the_tip_in_nearly_the_same_direction(name):
    """Poorly conditioned like a tendon finger: 5° to 30° between the inputs' tip directions."""
    plant = FingerPlant(PLANTS[name]())
    gain = plant.static_gain()
    assert 5.0 < input_angle(gain) < 30.0
    assert np.all(gain[1] > 0), 'positive torques close the finger (+Y)'


@pytest.mark.parametrize('name', ['flexor2_index', 'flexor2_thumb'])
def test_the_flexor_closes_the_extensor_opens_nearly_opposite(name):
    """Two antagonistic tendons that only pull: the flexor's tension moves the tip toward the
    palm (+Y), the extensor's away from it, 160° to 175° apart; neither pushes."""
    plant = FingerPlant(PLANTS[name]())
    gain = plant.static_gain()
    flexor, extensor = gain.T / np.linalg.norm(gain, axis=0)[:, None]
    assert 160.0 < np.degrees(np.arccos(flexor @ extensor)) < 175.0
    assert input_angle(gain) < 20.0                         # nearly one line, as tendon3's
    assert gain[1, 0] > 0 > gain[1, 1]
    assert plant.bounds == InputBounds([0.0, 0.0], [4.0, 4.0])


@pytest.mark.parametrize('name', ['tendon3_index', 'stiff2_a'])
def test_held_torques_settle_where_the_static_gain_points(name):
    """Each input alone, held on the frictionless finger, moves the tip along its column of the
    static gain (to within 2°, the curvature of a 0.1-limit step) and by its magnitude (±5 %)."""
    plant = FingerPlant(_frictionless(PLANTS[name]()))
    gain = plant.static_gain()
    u_size = 0.1 * plant.params.torque_limit
    moves = []
    for j in range(2):
        plant.reset()
        plant.step(u_size * np.eye(2)[j], 3.0)
        moves.append((plant.tip() - plant.rest_tip) / u_size)
    for j, move in enumerate(moves):
        cos = move @ gain[:, j] / (np.linalg.norm(move) * np.linalg.norm(gain[:, j]))
        assert np.degrees(np.arccos(min(1.0, cos))) < 2.0
        assert np.linalg.norm(move) == pytest.approx(np.linalg.norm(gain[:, j]), rel=0.05)
    assert 5.0 < input_angle(np.array(moves).T) < 30.0


@pytest.mark.parametrize('name', PLANTS)
def test_halving_the_step_moves_the_tip_after_one_second_by_less_than_a_micrometre(name):
    params = PLANTS[name]()
    tips = []
    for substep in (params.substep, params.substep / 2):
        plant = FingerPlant(dataclasses.replace(params, substep=substep))
        lim = params.torque_limit
        for k in range(200):                 # a 10 Hz square on u0, a 4 Hz one on u1, 5 ms ticks
            plant.step((0.6 * lim * (-1) ** (k // 5), 0.4 * lim * (-1) ** (k // 12)), 0.005)
        tips.append(plant.tip())
    assert np.max(np.abs(tips[0] - tips[1])) < 1 * UM


@pytest.mark.parametrize('name', PLANTS)
def test_coulomb_friction_leaves_a_steady_offset_unlike_the_frictionless_finger(name):
    """A torque below breakaway: the finger stops short of the frictionless equilibrium (the
    bristles carry part of the load) and stays there."""
    params = PLANTS[name]()
    u = (0.5 * params.coulomb[0] / params.transmission[0][0], 0.0)
    offsets = []
    for p in (params, _frictionless(params)):
        plant = FingerPlant(p)
        plant.step(u, 2.0)
        held = plant.tip()
        plant.step(u, 0.5)
        assert np.max(np.abs(plant.tip() - held)) < 0.01 * UM, 'settled'
        offsets.append(np.linalg.norm(held - plant.rest_tip))
    with_friction, frictionless = offsets
    static = np.linalg.norm(FingerPlant(params).static_gain() @ np.asarray(u))
    assert frictionless == pytest.approx(static, rel=0.02)
    assert 0.2 * frictionless < with_friction < 0.95 * frictionless
    assert frictionless - with_friction > 1 * UM


def test_friction_slides_at_its_coulomb_level():
    """Sliding steadily, the Dahl friction torque is ±F_c (below friction_speed)."""
    params = PLANTS['stiff2_a']()
    plant = FingerPlant(params)
    x = plant.rest_q.tolist() + [0.5, -0.3] + [0.0, 0.0]
    for _ in range(4000):                   # z relaxes at the constant rates q̇ (Euler, 0.1 ms)
        x[4:] = [z + 1e-4 * d for z, d in zip(x[4:], plant.derivative(x, [0.0, 0.0])[4:])]
    friction = np.asarray(params.presliding) * np.asarray(x[4:])
    np.testing.assert_allclose(friction, [params.coulomb[0], -params.coulomb[1]], rtol=1e-3)


def test_tendon_and_stiff_fingers_differ_threefold_in_speed():
    """First natural frequencies, from the linearisation and from free responses."""
    first = {name: FingerPlant(PLANTS[name]()).natural_frequencies()[0] for name in PLANTS}
    for name, seconds in (('tendon3_thumb', 4.0), ('stiff2_b', 1.0)):
        measured = _free_frequency(FingerPlant(_frictionless(PLANTS[name]())), seconds, 1e-3)
        assert measured == pytest.approx(first[name], rel=0.05), name
    slow = max(first[name] for name in PAIRS['tendon3'])
    fast = min(first[name] for name in PAIRS['stiff2'])
    assert fast >= 3 * slow
    assert all(2.0 < first[name] < 8.0 for name in PAIRS['tendon3'])
    assert all(15.0 < first[name] < 30.0 for name in PAIRS['stiff2'])
    zeta = {name: FingerPlant(PLANTS[name]()).modes()[1][0] for name in PAIRS['stiff2']}
    assert all(0.05 <= z <= 0.1 for z in zeta.values()), zeta


@pytest.mark.parametrize('kind, mm_per_mnm', [('tendon3', (0.5, 2.0)), ('stiff2', (0.005, 0.03))])
def test_pairs_rest_in_the_base_frame_and_move_at_their_scale(kind, mm_per_mnm):
    """Hanging (+X down), curled toward the palm (+Y); tendon fingers move about a millimetre
    per mN·m, stiff ones a few millimetres at their torque limit; the two fingers differ."""
    fingers = plant_pair(kind)
    assert [f.params.name for f in fingers] == list(PAIRS[kind])
    for f in fingers:
        assert 0.05 < f.rest_tip[0] < 0.1 and 0.0 < f.rest_tip[1] < 0.06
        gain = np.linalg.norm(f.static_gain(), axis=0)          # m/(N·m) = mm/(mN·m)
        assert np.all((mm_per_mnm[0] < gain) & (gain < mm_per_mnm[1]))
        if kind == 'stiff2':
            assert 1e-3 < np.min(gain) * f.params.torque_limit < 1e-2
    a, b = fingers
    assert a.params.tip_mass != b.params.tip_mass and a.params.stiffness != b.params.stiffness


def test_inputs_are_clipped_and_checked():
    params = PLANTS['tendon3_index']()
    clipped, at_limit = FingerPlant(params), FingerPlant(params)
    clipped.step((10.0, -10.0), 0.05)
    at_limit.step((params.torque_limit, -params.torque_limit), 0.05)
    np.testing.assert_array_equal(clipped.tip(), at_limit.tip())
    with pytest.raises(ValueError, match='finite'):
        clipped.step((np.nan, 0.0), 0.01)
    with pytest.raises(ValueError, match='two finite'):
        clipped.step((0.0, 0.0, 0.0), 0.01)
    with pytest.raises(ValueError, match='dt'):
        clipped.step((0.0, 0.0), -1.0)
    with pytest.raises(ValueError, match='unknown plant kind'):
        plant_pair('somo')


def test_a_substep_too_coarse_for_the_friction_is_refused():
    with pytest.raises(ValueError, match='too fast for RK4'):
        dataclasses.replace(PLANTS['stiff2_a'](), substep=1e-3)


@pytest.mark.parametrize('name', ['tendon3_thumb', 'stiff2_b'])
def test_the_written_out_derivatives_are_the_general_one(name):
    """The two- and three-joint fast paths compute the general derivative, in any state."""
    plant = FingerPlant(PLANTS[name]())
    general = plant.dynamics.general_derivative
    assert plant.derivative != general
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = np.concatenate([plant.rest_q + rng.normal(0, 0.5, plant.n),
                            rng.normal(0, 5, plant.n), rng.normal(0, 0.005, plant.n)]).tolist()
        tau = rng.normal(0, plant.params.torque_limit, plant.n).tolist()
        np.testing.assert_allclose(plant.derivative(x, tau), general(x, tau),
                                   rtol=1e-12, atol=1e-12)
