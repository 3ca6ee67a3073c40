"""A SoMo-faithful soft finger and four-finger hand in plain PyBullet (no ROS).

The finger is SoMo's in-hand-manipulation finger (see ``finger_spec.md``): ten rigid segments on
revolute joints with alternating axes (even joints bend about the link x axis, "ax0", the grasp
axis; odd joints about the link y axis, "ax1", the side axis), a linear spring on every joint and a
velocity motor with target 0 whose force limit acts as Coulomb-like joint friction. Every joint of
an axis receives the full actuator torque of that axis:

    τ_j = u[axis(j)] − k_axis(j) · q_j,        B = [[1,0],[0,1],[1,0],…] ∈ R^{10×2}.

Inside this module everything is in SoMo's scaled world (1 length unit = 0.05 m, torques ×400,
gravity 196.2 units/s²); the public API is SI (:mod:`soft_gripper_sdre.units`): torques in N·m in,
tip positions in metres out, each in its finger's own base frame.

Physics step: the stiffest linearised mode of the finger is ~329 Hz, and holding u = [25, 25]
sim units turns chaotic with 1 ms semi-implicit steps, so every control period is split into
``physics_substeps`` steps (default 2, i.e. 0.5 ms), which is stable over the paper's whole torque
range. Two runs with the same configuration are bit-identical.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
import json
import math
from pathlib import Path
import tempfile

import numpy as np
import pybullet as pb

from soft_gripper_sdre.units import LENGTH_SCALE, TORQUE_SCALE

SCENES = ('finger', 'hand')
N_JOINTS = 10
#: gravity in the scaled world [units/s²] (9.81 m/s² × 20)
GRAVITY = 9.81 * LENGTH_SCALE
WORLD_GRAVITY = (0.0, 0.0, -GRAVITY)
#: joint spring stiffness per axis [sim torque units / rad]
STIFFNESS = (87.4286, 414.857)
#: force limit of the velocity-0 motor that acts as joint friction [sim torque units]
FRICTION_TORQUE = 0.4
#: axis of each joint: 0 = ax0 (grasp, link x), 1 = ax1 (side, link y)
JOINT_AXIS = np.arange(N_JOINTS) % 2
#: B ∈ R^{10×2}: every joint of an axis receives the full actuator torque
B_MATRIX = np.stack([JOINT_AXIS == 0, JOINT_AXIS == 1], axis=1).astype(float)
JOINT_STIFFNESS = np.where(JOINT_AXIS == 0, STIFFNESS[0], STIFFNESS[1])
TIP_LINK = N_JOINTS - 1
#: (axis, k) of every joint as Python numbers, for the per-substep spring torques in plain floats
_SPRINGS = tuple(zip(JOINT_AXIS.tolist(), JOINT_STIFFNESS.tolist()))

#: hand layout (sim units): finger base positions, yaw per finger, roll of every finger
FINGER_BASE_POSITIONS = ((0.0, -0.7, 0.0), (0.7, 0.0, 0.0), (0.0, 0.7, 0.0), (-0.7, 0.0, 0.0))
FINGER_YAW_DEG = (0.0, 90.0, 180.0, 270.0)
FINGER_ROLL_DEG = 15.0
PALM = dict(radius=0.4, length=1.0, mass=1.5, center=(0.0, 0.0, 1.25), friction=0.15)
CUBE = dict(size=1.0, mass=0.01, center=(0.0, 0.0, 2.25), friction=1.2)
FINGER_FRICTION = 3.0
FINGER_RESTITUTION = 0.7


# ----------------------------------------------------------------------------------------------
# URDF generation
# ----------------------------------------------------------------------------------------------

def _inertial(mass: float, com: tuple, diag: tuple) -> str:
    return (f'<inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>'
            f'<mass value="{mass}"/>'
            f'<inertia ixx="{diag[0]}" ixy="0" ixz="0" iyy="{diag[1]}" iyz="0" izz="{diag[2]}"/>'
            f'</inertial>')


def _box(size: tuple, xyz: tuple) -> str:
    return (f'<collision><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
            f'<geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></collision>'
            f'<visual><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
            f'<geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></visual>')


def _finger_links(prefix: str = '') -> list[str]:
    """URDF elements of one finger: its base link (the root) and the 10-joint chain."""
    out = [f'<link name="{prefix}base">{_inertial(0.6, (0, 0, 0.1), (0.0225, 0.0225, 0.041))}'
           f'{_box((0.64, 0.64, 0.20), (0, 0, 0.10))}</link>']
    for j in range(N_JOINTS):
        if j == TIP_LINK:
            inertial = _inertial(0.01794, (0, 0, 0.083612), (1.08359e-3,) * 3)
        elif JOINT_AXIS[j] == 0:
            inertial = _inertial(0.00294294, (0, -0.00012, 0.0002), (8.2616e-5, 1.06513e-4, 8.2616e-5))
        else:
            inertial = _inertial(0.00294294, (0, 0, 0.0002), (6.3664e-5, 8.7560e-5, 8.2616e-5))
        height = 0.10 if j in (0, TIP_LINK) else 0.20
        # ax0 link frames sit 0.12 off the finger's centre line in y; the segments stay centred
        y_centre = -0.12 if JOINT_AXIS[j] == 0 else 0.0
        geometry = _box((0.46, 0.34, height), (0, y_centre, height / 2))
        if j == TIP_LINK:
            geometry += ('<collision><origin xyz="0 0.1 0.2" rpy="0 0 0"/>'
                         '<geometry><sphere radius="0.3"/></geometry></collision>')
        out.append(f'<link name="{prefix}link{j}">{inertial}{geometry}</link>')
        if j == 0:
            xyz = (0, 0.12, 0.30)
        elif JOINT_AXIS[j] == 1:
            xyz = (0, -0.12, 0.20)
        else:
            xyz = (0, 0.12, 0.20)
        axis = '1 0 0' if JOINT_AXIS[j] == 0 else '0 1 0'
        parent_link = f'{prefix}base' if j == 0 else f'{prefix}link{j - 1}'
        out.append(f'<joint name="{prefix}joint{j}" type="revolute"><parent link="{parent_link}"/>'
                   f'<child link="{prefix}link{j}"/><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0 0 0"/>'
                   f'<axis xyz="{axis}"/><limit lower="-3.141592" upper="3.141592" effort="1000" '
                   f'velocity="1000"/></joint>')
    return out


def finger_urdf() -> str:
    """URDF of one finger whose root is its base link (mounted by the base pose at load time)."""
    return '<?xml version="1.0"?>\n<robot name="ihm_finger">\n' + '\n'.join(
        _finger_links()) + '\n</robot>\n'


def load_fingers(client: int, poses: list[tuple[tuple, tuple]]) -> list[int]:
    """Load one finger (:func:`finger_urdf`, fixed base, inertia from the file) per base pose.

    Args:
        client: PyBullet physics client id.
        poses: (position, quaternion [x, y, z, w]) of each finger's base, sim units.

    Returns:
        The body id of each finger. PyBullet parses URDF from files only; the file is written to a
        temporary directory that is gone when this returns (the bodies do not need it).
    """
    with tempfile.TemporaryDirectory(prefix='sgs_urdf_') as d:
        path = Path(d) / 'finger.urdf'
        path.write_text(finger_urdf())
        return [pb.loadURDF(str(path), pos, orn, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE,
                            physicsClientId=client) for pos, orn in poses]


def finger_base_rpy(i: int) -> tuple[float, float, float]:
    """Roll-pitch-yaw of hand finger i's base: roll 15° about its x axis, then yaw.

    The roll is positive, so each finger leans away from the palm centre (a negative roll would
    put the fingertips inside the cube); +Y still points at the centre, so a negative u_ax0
    closes a finger toward the cube.
    """
    return (math.radians(FINGER_ROLL_DEG), 0.0, math.radians(FINGER_YAW_DEG[i]))


# ----------------------------------------------------------------------------------------------
# Simulator
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (SI at the boundary).

    Attributes:
        scene: ``'finger'`` (one finger, data collection) or ``'hand'`` (four fingers, palm, cube).
        control_period: duration of one :meth:`GripperSim.step` [s]; u is held over it.
        physics_substeps: physics steps per control period (physics dt = period / substeps).
        torque_limit: actuator limit; commands are clipped to ±limit [N·m].
        noise_std: standard deviation of the Gaussian noise on measured tip positions [m].
        seed: seed of the measurement noise.
        settle_time: time at u = 0 before t = 0; its end pose is the rest pose [s].
        mount_roll_deg: 'finger' scene only: roll of the base about its x axis. 15° mounts the
            finger exactly like a hand finger (so a model learned on it applies to each of them);
            0 is an upright finger.
        with_cube: 'hand' scene only: put the cube on the palm.
    """

    scene: str = 'hand'
    control_period: float = 1e-3
    physics_substeps: int = 2
    torque_limit: float = 0.1
    noise_std: float = 0.0
    seed: int = 0
    settle_time: float = 0.5
    mount_roll_deg: float = 15.0
    with_cube: bool = True

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f'scene must be one of {SCENES}, got {self.scene!r}')
        if not (math.isfinite(self.control_period) and 1e-5 <= self.control_period <= 0.1):
            raise ValueError(f'control_period must be in [1e-5, 0.1] s, got {self.control_period!r}')
        if not (isinstance(self.physics_substeps, int) and 1 <= self.physics_substeps <= 100):
            raise ValueError(f'physics_substeps must be an int in [1, 100], got {self.physics_substeps!r}')
        if not (math.isfinite(self.torque_limit) and self.torque_limit > 0):
            raise ValueError(f'torque_limit must be finite and > 0 N·m, got {self.torque_limit!r}')
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ValueError(f'noise_std must be finite and >= 0 m, got {self.noise_std!r}')
        if not (math.isfinite(self.settle_time) and self.settle_time >= 0):
            raise ValueError(f'settle_time must be finite and >= 0 s, got {self.settle_time!r}')
        if not math.isfinite(self.mount_roll_deg):
            raise ValueError(f'mount_roll_deg must be finite, got {self.mount_roll_deg!r}')

    @property
    def physics_dt(self) -> float:
        return self.control_period / self.physics_substeps

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


@dataclass(frozen=True)
class SimTruth:
    """Ground truth at the current time (SI, each finger in its own base frame)."""

    t: float
    q: np.ndarray                 # (n, 10) joint angles [rad]
    qd: np.ndarray                # (n, 10) joint velocities [rad/s]
    tip_pos: np.ndarray           # (n, 3) [m]
    tip_vel: np.ndarray           # (n, 3) [m/s]
    tip_acc: np.ndarray           # (n, 3) mean acceleration over the last control period [m/s²]
    u_applied: np.ndarray         # (n, 2) torque of the last step after clipping [N·m]
    cube_pose: np.ndarray | None  # (7,) [x, y, z, qx, qy, qz, qw] in the hand frame [m]
    finger_cube_contact: np.ndarray | None   # (n,) bool
    contact_force: np.ndarray | None         # (n,) normal force of each finger on the cube [N]


def _rot(rpy: tuple[float, float, float]) -> np.ndarray:
    """Rotation matrix of URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return np.array(pb.getMatrixFromQuaternion(pb.getQuaternionFromEuler(rpy))).reshape(3, 3)


class DirectClient:
    """A PyBullet DIRECT client that this object owns (``_client``): :meth:`close`, or leaving a
    ``with`` block, disconnects it."""

    def __init__(self) -> None:
        self._client = pb.connect(pb.DIRECT)

    def close(self) -> None:
        if self._client is not None and pb.isConnected(physicsClientId=self._client):
            pb.disconnect(physicsClientId=self._client)
        self._client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; close() is the API
        try:
            if getattr(self, '_client', None) is not None:
                self.close()
        except Exception:  # noqa: BLE001 — interpreter shutdown
            pass


class GripperSim(DirectClient):
    """The finger or the hand in its own PyBullet DIRECT client.

    Every PyBullet call names ``physicsClientId``, so several simulators can live in one process.
    Construction builds the world and settles it (:meth:`reset`).
    """

    def __init__(self, config: SimConfig | None = None) -> None:
        self.config = config or SimConfig()
        super().__init__()
        self.n_fingers = 1 if self.config.scene == 'finger' else 4
        self._rng = np.random.default_rng(self.config.seed)
        self.reset()

    # -- world construction ------------------------------------------------------------------
    def _build(self) -> None:
        cfg, cid = self.config, self._client
        pb.resetSimulation(physicsClientId=cid)
        pb.setGravity(*WORLD_GRAVITY, physicsClientId=cid)
        pb.setTimeStep(cfg.physics_dt, physicsClientId=cid)
        pb.setPhysicsEngineParameter(numSolverIterations=50, physicsClientId=cid)
        if cfg.scene == 'finger':
            rpys = [(math.radians(cfg.mount_roll_deg), 0.0, 0.0)]
            positions = [(0.0, 0.0, 0.0)]
        else:
            rpys = [finger_base_rpy(i) for i in range(4)]
            positions = list(FINGER_BASE_POSITIONS)
        # One multibody per finger: four 10-DoF chains solve far faster than one 40-DoF body
        # (the joint-friction motors are constraints whose cost grows with the body's DoF).
        self._bodies = load_fingers(cid, [(pos, pb.getQuaternionFromEuler(rpy))
                                          for pos, rpy in zip(positions, rpys)])
        self._base_pos = np.array(positions, dtype=float)
        self._base_rot = np.stack([_rot(rpy) for rpy in rpys])
        # per finger: p₀ and the columns of R (the rows of Rᵀ) as Python floats, for _read_state
        self._frames = [(p0.tolist(), R.T.tolist()) for p0, R in zip(self._base_pos, self._base_rot)]
        self._cube = self._palm = None
        if cfg.scene == 'hand':
            shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=PALM['radius'], height=PALM['length'],
                                            physicsClientId=cid)
            # the palm is fixed to the world (mass 0 = static); its nominal mass is irrelevant then
            self._palm = pb.createMultiBody(0.0, shape, -1, PALM['center'], physicsClientId=cid)
            pb.changeDynamics(self._palm, -1, lateralFriction=PALM['friction'], physicsClientId=cid)
            if cfg.with_cube:
                half = CUBE['size'] / 2
                shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[half] * 3, physicsClientId=cid)
                visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[half] * 3,
                                              rgbaColor=[0, 0.8, 0, 1], physicsClientId=cid)
                self._cube = pb.createMultiBody(CUBE['mass'], shape, visual, CUBE['center'],
                                                physicsClientId=cid)
                pb.changeDynamics(self._cube, -1, lateralFriction=CUBE['friction'], physicsClientId=cid)
        self._joint_list = list(range(N_JOINTS))
        zeros, friction = [0.0] * N_JOINTS, [FRICTION_TORQUE] * N_JOINTS
        for body in self._bodies:
            for link in range(-1, N_JOINTS):
                pb.changeDynamics(body, link, lateralFriction=FINGER_FRICTION,
                                  restitution=FINGER_RESTITUTION, physicsClientId=cid)
            # joint friction: a velocity-0 motor with a force limit, active under torque control too
            pb.setJointMotorControlArray(body, self._joint_list, pb.VELOCITY_CONTROL,
                                         targetVelocities=zeros, forces=friction, physicsClientId=cid)

    def reset(self) -> None:
        """Build a fresh world, settle ``settle_time`` at u = 0, and set t = 0 there."""
        self._build()
        self._u_sim = [[0.0, 0.0] for _ in range(self.n_fingers)]
        self._u_applied = np.zeros((self.n_fingers, 2))
        settle_steps = int(round(self.config.settle_time / self.config.physics_dt))
        self._read_joints()
        for _ in range(settle_steps):
            self._physics_step()
        self._steps = 0
        self._read_state()
        self._prev_vel = self._tip_vel        # tip_acc = (v − v) / Δt = 0 until the first step
        self.rest_tip = self._tip_pos.copy()
        self._draw_noise()

    # -- stepping ----------------------------------------------------------------------------
    def _read_joints(self) -> None:
        """Cache every joint's state as PyBullet returns it (per finger, per joint: angle, rate, …):
        the springs of the next physics step and :meth:`truth` both read this cache, so each state
        is fetched once, and turned into arrays only when :meth:`truth` asks."""
        cid, joints = self._client, self._joint_list
        self._joint_states = [pb.getJointStates(body, joints, physicsClientId=cid) for body in self._bodies]

    def _physics_step(self) -> None:
        cid, joints, torque = self._client, self._joint_list, pb.TORQUE_CONTROL
        for body, u, states in zip(self._bodies, self._u_sim, self._joint_states):
            # τ_j = u[axis(j)] − k_j q_j, in Python floats (the same IEEE operations as numpy's)
            tau = [u[axis] - k * state[0] for (axis, k), state in zip(_SPRINGS, states)]
            pb.setJointMotorControlArray(body, joints, torque, forces=tau, physicsClientId=cid)
        pb.stepSimulation(physicsClientId=cid)
        self._read_joints()

    def step(self, u) -> None:
        """Hold torques ``u`` (n, 2) [N·m] over one control period.

        Raises:
            ValueError: u has the wrong shape or non-finite entries (the state is unchanged).
        """
        u = np.asarray(u, dtype=float)
        if u.shape != (self.n_fingers, 2):
            raise ValueError(f'u must have shape ({self.n_fingers}, 2), got {u.shape}')
        if not np.isfinite(u).all():
            raise ValueError('u contains non-finite torques')
        lim = self.config.torque_limit
        self._u_applied = np.minimum(np.maximum(u, -lim), lim)      # clip to ±lim (u is finite)
        self._u_sim = (self._u_applied * TORQUE_SCALE).tolist()
        for _ in range(self.config.physics_substeps):
            self._physics_step()
        self._steps += 1
        self._prev_vel = self._tip_vel
        self._read_state()
        self._draw_noise()

    # -- reading -----------------------------------------------------------------------------
    def _read_state(self) -> None:
        cid, s = self._client, LENGTH_SCALE
        pos, vel = [], []
        for body, (p0, rot_t) in zip(self._bodies, self._frames):
            # link 9's centre of mass (the tip) and its velocity, in the world
            link = pb.getLinkState(body, TIP_LINK, computeLinkVelocity=1, physicsClientId=cid)
            (px, py, pz), (vx, vy, vz) = link[0], link[6]
            dx, dy, dz = px - p0[0], py - p0[1], pz - p0[2]
            # into the finger's base frame: p_b = Rᵀ (p − p₀), v_b = Rᵀ v, each row summed in
            # order j = 0, 1, 2 like numpy's einsum (a test checks the two are bit-identical)
            pos.append([(r0 * dx + r1 * dy + r2 * dz) / s for r0, r1, r2 in rot_t])
            vel.append([(r0 * vx + r1 * vy + r2 * vz) / s for r0, r1, r2 in rot_t])
        self._tip_pos, self._tip_vel = np.array(pos), np.array(vel)

    def _draw_noise(self) -> None:
        noise = (self._rng.standard_normal(self._tip_pos.shape) * self.config.noise_std
                 if self.config.noise_std > 0 else 0.0)
        self._measured = self._tip_pos + noise

    @property
    def t(self) -> float:
        """Time since the end of the settle [s]."""
        return self._steps * self.config.control_period

    @property
    def joint_names(self) -> list[str]:
        """``finger_<i>/joint_<j>`` for every joint, in the order of :attr:`SimTruth.q`."""
        return [f'finger_{i}/joint_{j}' for i in range(self.n_fingers) for j in range(N_JOINTS)]

    @property
    def base_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Each finger's base frame in the world: positions (n, 3) [m] and rotations (n, 3, 3)."""
        return self._base_pos / LENGTH_SCALE, self._base_rot.copy()

    def measure(self) -> np.ndarray:
        """(n, 3) measured tip positions [m] (noisy when ``noise_std`` > 0; one draw per step)."""
        return self._measured.copy()

    def truth(self) -> SimTruth:
        """Ground truth now."""
        cid = self._client
        q = np.array([[s[0] for s in states] for states in self._joint_states])
        qd = np.array([[s[1] for s in states] for states in self._joint_states])
        # mean acceleration over the last period: (v_k+1 − v_k) / Δt
        tip_acc = (self._tip_vel - self._prev_vel) / self.config.control_period
        cube_pose = contact = force = None
        if self._cube is not None:
            p, o = pb.getBasePositionAndOrientation(self._cube, physicsClientId=cid)
            cube_pose = np.array([*(x / LENGTH_SCALE for x in p), *o])
            # every contact of the cube in one call (bodyA = the cube, bodyB = the other body),
            # in the order a per-finger query lists them, so each finger's sum is the same
            sums = dict.fromkeys(self._bodies, 0.0)
            for c in pb.getContactPoints(self._cube, physicsClientId=cid):
                if c[2] in sums:
                    sums[c[2]] += c[9] / LENGTH_SCALE   # normal force, sim units (kg·unit/s²) → N
            force = np.array(list(sums.values()))
            contact = force > 0.0
        return SimTruth(self.t, q, qd, self._tip_pos.copy(), self._tip_vel.copy(),
                        tip_acc, self._u_applied.copy(), cube_pose, contact, force)

    # -- analysis helpers (ground truth for tests and evaluation) ----------------------------
    def linearize(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The finger linearised about its current pose with friction off, in SI (finger scene):
        M δq̈ + K δq = B u, tip position δp = J δq.

        M (10, 10) [kg·m²] and K (10, 10) [N·m/rad] (joint springs + gravity stiffness ∂g/∂q, by
        central differences of PyBullet's inverse dynamics with gravity as the mounted base sees
        it), B (10, 2) (u in N·m), and the tip Jacobian J (3, 10) [m/rad] in the finger's base
        frame (finite differences of the tip).
        """
        if self.config.scene != 'finger':
            raise ValueError('linearize is defined for the finger scene')
        cid = self._client
        body = self._bodies[0]
        states = pb.getJointStates(body, self._joint_list, physicsClientId=cid)
        q = [s[0] for s in states]
        M = np.array(pb.calculateMassMatrix(body, q, physicsClientId=cid))
        zeros = [0.0] * N_JOINTS
        h = 1e-6
        dg = np.zeros((N_JOINTS, N_JOINTS))
        J = np.zeros((3, N_JOINTS))
        rot = self._base_rot[0]
        # calculateInverseDynamics ignores a fixed base's orientation (gravity acts as if the finger
        # stood upright), so it runs with gravity turned into the base frame, g_b = Rᵀ (0, 0, −g),
        # as in dynamics.FingerDynamics; the world's gravity is put back right after
        pb.setGravity(*(rot.T @ np.array(WORLD_GRAVITY)).tolist(), physicsClientId=cid)
        try:
            for j in range(N_JOINTS):
                qp, qm = list(q), list(q)
                qp[j] += h
                qm[j] -= h
                gp = np.array(pb.calculateInverseDynamics(body, qp, zeros, zeros, physicsClientId=cid))
                gm = np.array(pb.calculateInverseDynamics(body, qm, zeros, zeros, physicsClientId=cid))
                dg[:, j] = (gp - gm) / (2 * h)                  # ∂g/∂q_j
        finally:
            pb.setGravity(*WORLD_GRAVITY, physicsClientId=cid)
        for j in range(N_JOINTS):
            qp, qm = list(q), list(q)
            qp[j] += h
            qm[j] -= h
            tips = []
            for qq in (qp, qm):
                for k in range(N_JOINTS):
                    pb.resetJointState(body, k, qq[k], physicsClientId=cid)
                tips.append(np.asarray(pb.getLinkState(body, TIP_LINK, physicsClientId=cid)[0]))
            J[:, j] = rot.T @ (tips[0] - tips[1]) / (2 * h)
        for k, st in enumerate(states):                       # put the finger back exactly
            pb.resetJointState(body, k, st[0], st[1], physicsClientId=cid)
        self._read_joints()
        # scaled world → SI: lengths /20, torques /400 (so inertia /400 too: τ = M q̈)
        K = (np.diag(JOINT_STIFFNESS) + dg) / TORQUE_SCALE
        return M / TORQUE_SCALE, K, B_MATRIX.copy(), J / LENGTH_SCALE

    def linear_modes(self) -> np.ndarray:
        """Natural frequencies [Hz] of the finger linearised about its current pose, friction off."""
        M, K, _, _ = self.linearize()
        w2 = np.linalg.eigvals(np.linalg.solve(M, K))
        return np.sort(np.sqrt(np.abs(w2.real))) / (2 * math.pi)
