"""The simulator against the SoMo figures of finger_spec.md (upright finger, sim units)."""
import xml.etree.ElementTree as ET

import numpy as np
import pybullet as pb
import pytest

from soft_gripper_sdre.sim.finger import GRAVITY, JOINT_AXIS, JOINT_STIFFNESS, finger_urdf
from soft_gripper_sdre.sim.hand import MAX_PHYSICS_DT, GripperSim, SimConfig, physics_substeps_for
from soft_gripper_sdre.sim.linear import linear_modes, linearize
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE

UPRIGHT = SimConfig(scene='finger', mount_roll_deg=0.0)


def held_deflection(u_sim, config=UPRIGHT, hold=8.0, average=2.0):
    """Spec protocol: settle 0.5 s at u = 0, step u on, hold, mean of the last 2 s (sim units)."""
    with GripperSim(config) as sim:
        rest = sim.rest_tip[0] * LENGTH_SCALE
        u = np.array([u_sim], dtype=float) / TORQUE_SCALE
        n, n_avg = int(round(hold / 1e-3)), int(round(average / 1e-3))
        tips = []
        for k in range(n):
            sim.step(u)
            if k >= n - n_avg:
                tips.append(sim.truth().tip_pos[0] * LENGTH_SCALE)
        tips = np.array(tips)
    return tips.mean(axis=0) - rest, tips


def test_settled_rest_pose_matches_somo():
    with GripperSim(UPRIGHT) as sim:
        rest = sim.rest_tip[0] * LENGTH_SCALE
    np.testing.assert_allclose(rest, [0.0, -0.0429, 2.1791], atol=3e-3)


@pytest.mark.parametrize('u, dx, dy', [((10, 10), 0.103, -0.729), ((-10, -10), None, 0.813)])
def test_static_deflection(u, dx, dy):
    d, _ = held_deflection(u)
    assert d[1] == pytest.approx(dy, rel=0.05)
    if dx is not None:
        assert d[0] == pytest.approx(dx, rel=0.10)


def test_linearised_modes_match_somo():
    with GripperSim(UPRIGHT) as sim:
        modes = linear_modes(sim)
    assert modes[0] == pytest.approx(3.07, rel=0.05)
    assert modes[1] == pytest.approx(8.92, rel=0.05)


@pytest.mark.parametrize('u', [25.0, -25.0])
def test_full_torque_held_is_stable_and_settles(u):
    _, tips = held_deflection((u, u), hold=5.0, average=1.0)
    assert np.all(np.isfinite(tips))
    assert np.all(np.abs(tips) < 5.0)                 # bounded: the finger is 2.2 units long
    assert np.all(tips.std(axis=0) < 1e-3)            # settled: no chaotic ringing in the last 1 s


@pytest.mark.parametrize('axis, tip_axis, sign', [(0, 1, -1), (1, 0, +1)])
def test_input_signs(axis, tip_axis, sign):
    """+u_ax0 bends the tip toward −Y, +u_ax1 toward +X (finger base frame)."""
    u = [0.0, 0.0]
    u[axis] = 5.0
    d, _ = held_deflection(u, config=SimConfig(scene='finger'), hold=1.0, average=0.2)
    assert np.sign(d[tip_axis]) == sign and abs(d[tip_axis]) > 0.02


def test_negative_grasp_torque_closes_hand_fingers_on_the_cube():
    with GripperSim(SimConfig(scene='hand')) as sim:
        cube0 = sim.truth().cube_pose
        u = np.zeros((4, 2))
        u[[0, 2], 0] = -8.0 / TORQUE_SCALE
        for _ in range(600):
            sim.step(u)
        truth = sim.truth()
    travel = truth.tip_pos[:, 1] - sim.rest_tip[:, 1]
    assert travel[0] > 0.02 and travel[2] > 0.02               # +Y: toward the palm centre
    assert truth.finger_cube_contact.tolist() == [True, False, True, False]
    assert np.all(truth.contact_force[[0, 2]] > 0)
    assert np.linalg.norm(truth.cube_pose[:3] - cube0[:3]) < 2e-3   # squeezed, not pushed away


def test_hand_fingers_share_the_same_kinematics_in_their_base_frames():
    with (GripperSim(SimConfig(scene='hand')) as hand,
          GripperSim(SimConfig(scene='finger')) as finger):
        np.testing.assert_allclose(hand.rest_tip, np.repeat(finger.rest_tip, 4, axis=0), atol=1e-9)


def test_lockstep_runs_are_bit_identical():
    def run():
        with GripperSim(SimConfig(scene='hand', noise_std=5e-5, seed=3)) as sim:
            out = []
            for k in range(300):
                u = np.full((4, 2), 0.02 * np.sin(0.01 * k))
                sim.step(u)
                out.append(np.concatenate([sim.measure().ravel(), sim.truth().q.ravel()]))
        return np.array(out)
    a, b = run(), run()
    assert np.array_equal(a, b)


def test_measurement_noise_is_seeded_and_sized():
    with GripperSim(SimConfig(scene='finger', noise_std=1e-4, seed=1)) as sim:
        errs = []
        for _ in range(400):
            sim.step(np.zeros((1, 2)))
            errs.append(sim.measure()[0] - sim.truth().tip_pos[0])
        assert np.array_equal(sim.measure(), sim.measure())     # one draw per step
    assert np.std(errs) == pytest.approx(1e-4, rel=0.1)


def test_truth_acceleration_is_the_velocity_change_over_the_period():
    with GripperSim(SimConfig(scene='finger')) as sim:
        v0 = sim.truth().tip_vel
        sim.step(np.array([[0.03, 0.01]]))
        tr = sim.truth()
    np.testing.assert_allclose(tr.tip_acc, (tr.tip_vel - v0) / 1e-3)
    assert np.abs(tr.tip_acc).max() > 0


def test_torques_are_clipped_to_the_limit():
    with GripperSim(SimConfig(scene='finger', torque_limit=0.05)) as sim:
        sim.step(np.array([[1.0, -1.0]]))
        np.testing.assert_allclose(sim.truth().u_applied, [[0.05, -0.05]])


@pytest.mark.parametrize('u, match', [
    (np.zeros((2, 2)), 'shape'), (np.array([[np.nan, 0.0]]), 'non-finite'),
    (np.array([[np.inf, 0.0]]), 'non-finite')])
def test_bad_torques_rejected_and_state_unchanged(u, match):
    with GripperSim(SimConfig(scene='finger')) as sim:
        sim.step(np.array([[0.01, 0.0]]))
        before = sim.truth()
        with pytest.raises(ValueError, match=match):
            sim.step(u)
        after = sim.truth()
        assert after.t == before.t and np.array_equal(after.q, before.q)


@pytest.mark.parametrize('kwargs, field', [
    (dict(scene='arm'), 'scene'), (dict(control_period=-1e-3), 'control_period'),
    (dict(physics_substeps=0), 'physics_substeps'), (dict(torque_limit=0.0), 'torque_limit'),
    (dict(noise_std=-1.0), 'noise_std'), (dict(settle_time=float('nan')), 'settle_time')])
def test_bad_config_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SimConfig(**kwargs)


@pytest.mark.parametrize('period, substeps', [(1e-3, 2), (2e-3, 4), (3e-3, 6), (5e-3, 10),
                                              (1e-2, 20), (7e-4, 2), (2e-4, 1)])
def test_default_substeps_keep_the_physics_step_at_most_half_a_millisecond(period, substeps):
    cfg = SimConfig(control_period=period)
    assert cfg.physics_substeps == physics_substeps_for(period) == substeps
    assert cfg.physics_dt <= MAX_PHYSICS_DT * (1 + 1e-12)
    assert SimConfig(control_period=period, physics_substeps=3).physics_substeps == 3


def test_two_simulators_live_in_one_process():
    """Explicit physicsClientId everywhere: interleaved simulators do not disturb each other."""
    with GripperSim(SimConfig(scene='finger')) as alone:
        for _ in range(50):
            alone.step(np.zeros((1, 2)))
        expected = alone.truth().tip_pos
    with GripperSim(SimConfig(scene='finger')) as a, GripperSim(SimConfig(scene='finger')) as b:
        for _ in range(50):
            a.step(np.array([[0.02, 0.0]]))
            b.step(np.zeros((1, 2)))
        assert np.array_equal(b.truth().tip_pos, expected)
        assert not np.allclose(a.truth().tip_pos, expected)


def test_stepping_equals_the_straightforward_numpy_computation():
    """The plain-float fast paths (spring torques, clip, tip frames, cube contact sums) give the
    same bits as the direct numpy/PyBullet computation, in a grasp with contacts."""
    cfg = SimConfig(scene='hand', settle_time=0.2)
    u = np.zeros((4, 2))
    u[[0, 2], 0] = -0.05
    u[[1, 3]] = [0.3, -0.01]                           # beyond the limit: clipped
    with GripperSim(cfg) as sim, GripperSim(cfg) as ref:
        cid, bodies, joints = ref.physics_client, ref.finger_bodies, list(range(10))
        base_pos, base_rot = ref.base_poses

        def ref_joints():
            states = [pb.getJointStates(b, joints, physicsClientId=cid) for b in bodies]
            return (np.array([[s[0] for s in st] for st in states]),
                    np.array([[s[1] for s in st] for st in states]))
        for _ in range(300):
            sim.step(u)
            u_sim = np.clip(u, -cfg.torque_limit, cfg.torque_limit) * TORQUE_SCALE
            for _ in range(cfg.physics_substeps):
                q, _ = ref_joints()
                tau = u_sim[:, JOINT_AXIS] - JOINT_STIFFNESS * q          # τ = B u − K q
                for b, t in zip(bodies, tau.tolist()):
                    pb.setJointMotorControlArray(b, joints, pb.TORQUE_CONTROL, forces=t,
                                                 physicsClientId=cid)
                pb.stepSimulation(physicsClientId=cid)
        tr = sim.truth()
        q, qd = ref_joints()
        links = [pb.getLinkState(b, 9, computeLinkVelocity=1, computeForwardKinematics=1,
                                 physicsClientId=cid) for b in bodies]
        # p_b = Rᵀ (p − p₀) in sim units, then → m
        pos = np.einsum('nji,nj->ni', base_rot,
                        np.array([ls[0] for ls in links]) - base_pos * LENGTH_SCALE)
        force = np.zeros(4)
        for i, b in enumerate(bodies):
            for c in pb.getContactPoints(b, ref.cube_body, physicsClientId=cid):
                force[i] += c[9] / LENGTH_SCALE
        assert np.array_equal(tr.q, q) and np.array_equal(tr.qd, qd)
        assert np.array_equal(tr.u_applied, np.clip(u, -0.1, 0.1))
        assert np.array_equal(tr.tip_pos, pos / LENGTH_SCALE)
        assert tr.finger_cube_contact.tolist() == [True, False, True, False]
        assert np.array_equal(tr.contact_force, force)


def test_tip_frames_equal_numpys_einsum_bit_for_bit():
    """The tips are turned into each finger's base frame in plain floats, summed in einsum's order:
    the same bits as numpy on the hand's four frames (roll 15°, yaw 0/90/180/270°)."""
    rng = np.random.default_rng(0)
    with GripperSim(SimConfig(scene='hand', settle_time=0.0)) as sim:
        base_pos, base_rot = sim.base_poses
        base_pos = base_pos * LENGTH_SCALE
        for _ in range(20):
            sim.step(rng.uniform(-0.1, 0.1, (4, 2)))
            links = [pb.getLinkState(b, 9, computeLinkVelocity=1, computeForwardKinematics=1,
                                     physicsClientId=sim.physics_client) for b in sim.finger_bodies]
            p, v = np.array([ls[0] for ls in links]), np.array([ls[6] for ls in links])
            p_b = np.einsum('nji,nj->ni', base_rot, p - base_pos)     # Rᵀ (p − p₀)
            truth = sim.truth()
            assert np.array_equal(truth.tip_pos, p_b / LENGTH_SCALE)
            assert np.array_equal(truth.tip_vel,
                                  np.einsum('nji,nj->ni', base_rot, v) / LENGTH_SCALE)


def urdf_tip_kinematics(q, qd):
    """Tip position [sim units] and velocity [sim units/s] in the finger's base frame, from the
    joint state and the URDF alone (joint origins, axes and link 9's inertial origin): the tip the
    simulator should report, computed without PyBullet."""
    robot = ET.fromstring(finger_urdf().split('\n', 1)[1])     # without the XML declaration
    floats = lambda text: np.array([float(v) for v in text.split()])  # noqa: E731
    joints = robot.findall('joint')
    tip_link = joints[-1].find('child').get('link')
    com = floats(robot.find(f"link[@name='{tip_link}']/inertial/origin").get('xyz'))
    R, p, origins, axes = np.eye(3), np.zeros(3), [], []
    for joint, angle in zip(joints, q):
        p = p + R @ floats(joint.find('origin').get('xyz'))
        a = floats(joint.find('axis').get('xyz'))
        k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        R = R @ (np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k)     # Rodrigues
        origins.append(p)
        axes.append(R @ a)
    tip = p + R @ com
    return tip, sum(w * np.cross(a, tip - o) for w, a, o in zip(qd, axes, origins))


@pytest.mark.parametrize('scene', ['finger', 'hand'])
def test_reported_tip_is_the_forward_kinematics_of_the_reported_joint_state(scene):
    """truth() and measure() give the tip of the joint state truth() reports, not of the state one
    physics substep earlier, to machine precision, while the fingers swing fast."""
    with GripperSim(SimConfig(scene=scene, settle_time=0.1)) as sim:
        n = sim.n_fingers
        for k in range(300):
            sim.step(np.tile([[0.03 * np.sin(0.02 * k), 0.02 * np.cos(0.05 * k)]], (n, 1)))
            if k % 10:
                continue
            truth = sim.truth()
            for i in range(n):
                tip, vel = urdf_tip_kinematics(truth.q[i], truth.qd[i])
                # a few ulps of the 0.1 m tip and the ~1 m/s speeds of this motion
                np.testing.assert_allclose(truth.tip_pos[i], tip / LENGTH_SCALE, rtol=0, atol=1e-15)
                np.testing.assert_allclose(truth.tip_vel[i], vel / LENGTH_SCALE, rtol=0, atol=1e-14)
            assert np.array_equal(sim.measure(), truth.tip_pos)
        assert np.abs(truth.tip_vel).max() > 0.3         # the check ran on a moving finger


def _potential_hessian(sim, h=1e-3):
    """∂²V/∂q² [sim torque units/rad] of the gravity potential V(q) = Σ m_l g z_l(q), by central
    differences of the links' world centres of mass (the base as mounted), finger scene."""
    body, cid = sim.finger_bodies[0], sim.physics_client
    masses = [pb.getDynamicsInfo(body, link, physicsClientId=cid)[0] for link in range(10)]
    q0 = sim.truth().q[0]

    def V(q):
        for j in range(10):
            pb.resetJointState(body, j, q[j], physicsClientId=cid)
        return sum(m * GRAVITY * pb.getLinkState(body, link, physicsClientId=cid)[0][2]
                   for link, m in enumerate(masses))
    H, E = np.zeros((10, 10)), np.eye(10) * h
    for j in range(10):
        for k in range(j, 10):
            H[j, k] = H[k, j] = (V(q0 + E[j] + E[k]) - V(q0 + E[j] - E[k]) - V(q0 - E[j] + E[k])
                                 + V(q0 - E[j] - E[k])) / (4 * h * h)
    return H


@pytest.mark.parametrize('roll', [15.0, 0.0])
def test_linearized_stiffness_is_springs_plus_the_gravity_potentials_hessian(roll):
    """K = K_springs + ∂²V/∂q² with gravity as the mounted base sees it (PyBullet's inverse
    dynamics alone would treat a rolled base as upright)."""
    with GripperSim(SimConfig(scene='finger', mount_roll_deg=roll)) as sim:
        for _ in range(300):
            sim.step(np.array([[-0.04, 0.03]]))
        M, K, _, _ = linearize(sim)
        H = _potential_hessian(sim)
    K_gravity = K - np.diag(JOINT_STIFFNESS) / TORQUE_SCALE
    np.testing.assert_allclose(K_gravity, H / TORQUE_SCALE, rtol=0,
                               atol=1e-4 * np.abs(H).max() / TORQUE_SCALE)


def test_linearize_leaves_the_run_unchanged():
    """linearize moves the joints and turns gravity for its differences; it puts both back
    exactly."""
    def run(linearize_at):
        with GripperSim(SimConfig(scene='finger')) as sim:
            out = []
            for k in range(400):
                sim.step(np.array([[0.03 * np.sin(0.01 * k), -0.02]]))
                if k == linearize_at:
                    linearize(sim)
                out.append(np.concatenate([sim.truth().q[0], sim.truth().qd[0]]))
        return np.array(out)
    assert np.array_equal(run(None), run(100))
