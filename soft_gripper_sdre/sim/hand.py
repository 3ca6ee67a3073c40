"""The simulated finger or four-finger hand, stepped at the control period (no ROS).

:class:`GripperSim` builds the scene of :mod:`soft_gripper_sdre.sim.finger`
(:func:`~soft_gripper_sdre.sim.scene.build_scene`) in its own PyBullet DIRECT client and exposes it
in SI: torques in N·m in, tip positions in metres out, each in its finger's own base frame.

Physics step: the stiffest linearised mode of the finger is ~329 Hz, and holding u = [25, 25]
sim units turns chaotic with 1 ms semi-implicit steps, so every control period is split into
``physics_substeps`` steps. By default they are the fewest of at most :data:`MAX_PHYSICS_DT`
(0.5 ms: 2 at the 1 ms control period, 20 at 10 ms), which is stable over the paper's whole
torque range. Two runs with the same configuration are bit-identical.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
import json
import math

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.finger import (
    JOINT_SPRINGS,
    N_JOINTS,
    SCENES,
    TIP_LINK,
    WORLD_GRAVITY,
    DirectClient,
)
from soft_gripper_sdre.sim.plant import PlantVariation
from soft_gripper_sdre.sim.scene import build_scene
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE

#: the longest physics step the default substeps allow [s]
MAX_PHYSICS_DT = 5e-4


def physics_substeps_for(control_period: float) -> int:
    """The fewest physics steps per control period that are each at most :data:`MAX_PHYSICS_DT`."""
    return max(1, math.ceil(control_period / MAX_PHYSICS_DT - 1e-9))


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (SI at the boundary).

    Attributes:
        scene: ``'finger'`` (one finger, data collection) or ``'hand'`` (four fingers, palm, cube).
        control_period: duration of one :meth:`GripperSim.step` [s]; u is held over it.
        physics_substeps: physics steps per control period (physics dt = period / substeps);
            None: :func:`physics_substeps_for` the period.
        torque_limit: actuator limit; commands are clipped to ±limit [N·m].
        noise_std: standard deviation of the Gaussian noise on measured tip positions [m].
        seed: seed of the measurement noise.
        settle_time: time at u = 0 before t = 0; its end pose is the rest pose [s].
        mount_roll_deg: 'finger' scene only: roll of the base about its x axis. 15° mounts the
            finger exactly like a hand finger (so a model learned on it applies to each of them);
            0 is an upright finger.
        with_cube: 'hand' scene only: put the cube on the palm.
        plant: scales on the finger's stiffness, friction, tip mass and the cube's mass
            (:class:`~soft_gripper_sdre.sim.plant.PlantVariation`; default: the nominal plant).
    """

    scene: str = 'hand'
    control_period: float = 1e-3
    physics_substeps: int | None = None
    torque_limit: float = 0.1
    noise_std: float = 0.0
    seed: int = 0
    settle_time: float = 0.5
    mount_roll_deg: float = 15.0
    with_cube: bool = True
    plant: PlantVariation = field(default_factory=PlantVariation)

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f'scene must be one of {SCENES}, got {self.scene!r}')
        if not (math.isfinite(self.control_period) and 1e-5 <= self.control_period <= 0.1):
            raise ValueError(f'control_period must be in [1e-5, 0.1] s, '
                             f'got {self.control_period!r}')
        if self.physics_substeps is None:
            object.__setattr__(self, 'physics_substeps', physics_substeps_for(self.control_period))
        if not (isinstance(self.physics_substeps, int) and 1 <= self.physics_substeps <= 100):
            raise ValueError(f'physics_substeps must be an int in [1, 100], '
                             f'got {self.physics_substeps!r}')
        if not (math.isfinite(self.torque_limit) and self.torque_limit > 0):
            raise ValueError(f'torque_limit must be finite and > 0 N·m, got {self.torque_limit!r}')
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ValueError(f'noise_std must be finite and >= 0 m, got {self.noise_std!r}')
        if not (math.isfinite(self.settle_time) and self.settle_time >= 0):
            raise ValueError(f'settle_time must be finite and >= 0 s, got {self.settle_time!r}')
        if not math.isfinite(self.mount_roll_deg):
            raise ValueError(f'mount_roll_deg must be finite, got {self.mount_roll_deg!r}')
        if not isinstance(self.plant, PlantVariation):
            raise ValueError(f'plant must be a PlantVariation, got {type(self.plant).__name__}')

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
        # (axis, k) of every joint with the plant's stiffness, read by every physics step
        self._springs = tuple((axis, k * cfg.plant.stiffness_scale) for axis, k in JOINT_SPRINGS)
        pb.resetSimulation(physicsClientId=cid)
        pb.setGravity(*WORLD_GRAVITY, physicsClientId=cid)
        pb.setTimeStep(cfg.physics_dt, physicsClientId=cid)
        pb.setPhysicsEngineParameter(numSolverIterations=50, physicsClientId=cid)
        self._scene = build_scene(cid, cfg.scene, cfg.mount_roll_deg, cfg.with_cube, cfg.plant)
        self._bodies, self._cube = self._scene.fingers, self._scene.cube
        # per finger: p₀ and the columns of R (the rows of Rᵀ) as Python floats, for _read_state
        self._frames = [(p0.tolist(), R.T.tolist())
                        for p0, R in zip(self._scene.base_pos, self._scene.base_rot)]
        self._joint_list = list(range(N_JOINTS))

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
        self._joint_states = [pb.getJointStates(body, joints, physicsClientId=cid)
                              for body in self._bodies]

    def _physics_step(self) -> None:
        cid, joints, torque = self._client, self._joint_list, pb.TORQUE_CONTROL
        for body, u, states in zip(self._bodies, self._u_sim, self._joint_states):
            # τ_j = u[axis(j)] − k_j q_j, in Python floats (the same IEEE operations as numpy's)
            tau = [u[axis] - k * state[0] for (axis, k), state in zip(self._springs, states)]
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
            # link 9's centre of mass (the tip) and its velocity, in the world. PyBullet's cached
            # link frames are those of the state before the last physics step; recomputing the
            # forward kinematics makes the tip that of the joint state the step ended in (the one
            # truth() reports)
            link = pb.getLinkState(body, TIP_LINK, computeLinkVelocity=1,
                                   computeForwardKinematics=1, physicsClientId=cid)
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
    def physics_client(self) -> int:
        """The PyBullet client id of this simulator (for direct PyBullet queries in analysis and
        tests)."""
        return self._client

    @property
    def finger_bodies(self) -> tuple[int, ...]:
        """PyBullet body id of each finger, in finger order."""
        return tuple(self._bodies)

    @property
    def cube_body(self) -> int | None:
        """PyBullet body id of the cube (None without a cube)."""
        return self._cube

    @property
    def base_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Each finger's base frame in the world: positions (n, 3) [m] and rotations (n, 3, 3)."""
        return self._scene.base_pos / LENGTH_SCALE, self._scene.base_rot.copy()

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
