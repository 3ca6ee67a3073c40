"""The hand drawn from a recorded run: PyBullet's CPU renderer, no display, no GPU, no ROS.

:class:`HandScene` rebuilds the simulator's hand (:mod:`soft_gripper_sdre.sim.finger`: the same
finger URDF, base poses, palm and cube) in its own PyBullet DIRECT client, with visual shapes only
and no physics: each frame poses the fingers from recorded joint angles and the cube from its
recorded pose, then renders with ``ER_TINY_RENDERER``. :meth:`HandScene.project` maps world
points to pixels through the same view and projection matrices, so tips and references can be
drawn over a frame exactly where the renderer put them.

:func:`replay` turns a :class:`~soft_gripper_sdre.analysis.bag.Run` into :class:`Frame` objects at
chosen instants: the image, its segmentation, and each finger's true tip (the link-9 centre of
mass, the controlled point) and reference, in pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as pb

from soft_gripper_sdre.sim.finger import (
    CUBE,
    FINGER_BASE_POSITIONS,
    N_JOINTS,
    PALM,
    TIP_LINK,
    DirectClient,
    finger_base_rpy,
    load_fingers,
    rpy_matrix,
)
from soft_gripper_sdre.sim.units import LENGTH_SCALE

#: the hand's fingers that grasp the cube (they face each other across it)
GRASPING = (0, 2)
#: where the camera looks from: target (sim units), distance, yaw, pitch [deg]
CAMERA = dict(target=(0.0, 0.0, 1.55), distance=5.6, yaw=90.0, pitch=-28.0)
#: the fingertip's collision sphere in link 9's frame (sim units), as sim/finger.py builds it
TIP_SPHERE = dict(radius=0.3, offset=(0.0, 0.1, 0.2))
COLOURS = dict(grasping=(0.33, 0.55, 0.85, 1.0), other=(0.78, 0.78, 0.80, 1.0),
               base=(0.35, 0.35, 0.38, 1.0), palm=(0.45, 0.45, 0.48, 1.0),
               cube=(0.0, 0.75, 0.0, 1.0))


@dataclass(frozen=True)
class Frame:
    """One rendered instant (pixels: column u to the right, row v down)."""

    t: float                   # sim time [s]
    rgb: np.ndarray            # (H, W, 3) uint8
    segmentation: np.ndarray   # (H, W) body id per pixel, -1 background
    tips_px: np.ndarray        # (n, 2) each finger's true tip (link 9 centre of mass)
    refs_px: np.ndarray        # (n, 2) each finger's reference (NaN where none is in force)
    cube_px: np.ndarray | None  # (2,) the cube's centre
    cube_body: int | None      # the cube's id in ``segmentation``
    errors_mm: np.ndarray      # (n,) each finger's 2-D distance of the true tip from its reference

    def cube_pixels(self) -> np.ndarray:
        """(K, 2) [u, v] of the pixels that show the cube."""
        if self.cube_body is None:
            return np.empty((0, 2))
        v, u = np.nonzero(self.segmentation == self.cube_body)
        return np.stack([u, v], axis=1).astype(float)


class HandScene(DirectClient):
    """The four-finger hand with palm and cube, posed by hand, rendered on the CPU.

    Args:
        width, height: image size [px].
        camera: :data:`CAMERA` keys; any not given keep their default.
        with_cube: draw the cube.
    """

    def __init__(self, width: int = 480, height: int = 360, camera: dict | None = None,
                 with_cube: bool = True) -> None:
        super().__init__()
        if width < 16 or height < 16:
            raise ValueError(f'image size must be at least 16 x 16 px, got {width} x {height}')
        self.width, self.height = int(width), int(height)
        cam = dict(CAMERA, **(camera or {}))
        self.view = pb.computeViewMatrixFromYawPitchRoll(cam['target'], cam['distance'], cam['yaw'],
                                                         cam['pitch'], 0.0, 2)
        self.projection = pb.computeProjectionMatrixFOV(38.0, self.width / self.height, 0.1, 50.0)
        # clip = P V x, with PyBullet's column-major matrices
        self._pv = (np.array(self.projection).reshape(4, 4).T @ np.array(self.view).reshape(4, 4).T)
        cid = self._client
        rpys = [finger_base_rpy(i) for i in range(len(FINGER_BASE_POSITIONS))]
        self.base_pos = np.array(FINGER_BASE_POSITIONS, dtype=float)
        self.base_rot = np.stack([rpy_matrix(rpy) for rpy in rpys])
        self.fingers = load_fingers(cid, [(pos, pb.getQuaternionFromEuler(rpy))
                                          for pos, rpy in zip(FINGER_BASE_POSITIONS, rpys)])
        for i, body in enumerate(self.fingers):
            colour = COLOURS['grasping'] if i in GRASPING else COLOURS['other']
            pb.changeVisualShape(body, -1, rgbaColor=COLOURS['base'], physicsClientId=cid)
            for link in range(N_JOINTS):
                pb.changeVisualShape(body, link, rgbaColor=colour, physicsClientId=cid)
        self.tip_spheres = []
        for i in range(len(self.fingers)):
            colour = COLOURS['grasping'] if i in GRASPING else COLOURS['other']
            sphere = pb.createVisualShape(pb.GEOM_SPHERE, radius=TIP_SPHERE['radius'],
                                          rgbaColor=colour, physicsClientId=cid)
            self.tip_spheres.append(pb.createMultiBody(0.0, -1, sphere, (0, 0, -10),
                                                        physicsClientId=cid))
        palm = pb.createVisualShape(pb.GEOM_CYLINDER, radius=PALM['radius'], length=PALM['length'],
                                    rgbaColor=COLOURS['palm'], physicsClientId=cid)
        self.palm = pb.createMultiBody(0.0, -1, palm, PALM['center'], physicsClientId=cid)
        self.cube = None
        if with_cube:
            cube = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[CUBE['size'] / 2] * 3,
                                        rgbaColor=COLOURS['cube'], physicsClientId=cid)
            self.cube = pb.createMultiBody(0.0, -1, cube, CUBE['center'], physicsClientId=cid)
        self.set_pose(np.zeros((len(self.fingers), N_JOINTS)))

    # -- posing ------------------------------------------------------------------------------
    def set_pose(self, q: np.ndarray, cube_pose: np.ndarray | None = None) -> None:
        """Pose every finger with ``q`` (4, 10) [rad] and the cube with ``cube_pose``
        [x, y, z (m), qx, qy, qz, qw] in the hand frame (None: where it is)."""
        cid = self._client
        q = np.asarray(q, dtype=float)
        if q.shape != (len(self.fingers), N_JOINTS):
            raise ValueError(f'q must have shape ({len(self.fingers)}, {N_JOINTS}), got {q.shape}')
        for body, angles, sphere in zip(self.fingers, q.tolist(), self.tip_spheres):
            for j, angle in enumerate(angles):
                pb.resetJointState(body, j, angle, 0.0, physicsClientId=cid)
            link = pb.getLinkState(body, TIP_LINK, computeForwardKinematics=1, physicsClientId=cid)
            rot = np.array(pb.getMatrixFromQuaternion(link[5])).reshape(3, 3)
            centre = np.array(link[4]) + rot @ np.array(TIP_SPHERE['offset'])
            pb.resetBasePositionAndOrientation(sphere, centre.tolist(), link[5],
                                               physicsClientId=cid)
        if cube_pose is not None and self.cube is not None:
            c = np.asarray(cube_pose, dtype=float)
            pb.resetBasePositionAndOrientation(self.cube, (c[:3] * LENGTH_SCALE).tolist(),
                                               c[3:7].tolist(), physicsClientId=cid)

    def tips_world(self) -> np.ndarray:
        """(4, 3) each finger's controlled point (link 9's centre of mass), world, sim units."""
        return np.array([pb.getLinkState(body, TIP_LINK, computeForwardKinematics=1,
                                         physicsClientId=self._client)[0] for body in self.fingers])

    def cube_world(self) -> np.ndarray | None:
        """(3,) the cube's centre, world, sim units (None without a cube)."""
        if self.cube is None:
            return None
        pose = pb.getBasePositionAndOrientation(self.cube, physicsClientId=self._client)
        return np.array(pose[0])

    def to_world(self, finger: int, p_base: np.ndarray) -> np.ndarray:
        """Points (…, 3) [m] in finger ``finger``'s base frame → world, sim units."""
        return self.base_pos[finger] + (np.asarray(p_base) * LENGTH_SCALE) @ self.base_rot[finger].T

    def to_base(self, finger: int, p_world: np.ndarray) -> np.ndarray:
        """Points (…, 3) world, sim units → finger ``finger``'s base frame [m]."""
        offset = np.asarray(p_world) - self.base_pos[finger]
        return (offset @ self.base_rot[finger]) / LENGTH_SCALE

    # -- drawing -----------------------------------------------------------------------------
    def render(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 image and (H, W) segmentation (body id per pixel, -1 background)."""
        w, h = self.width, self.height
        img = pb.getCameraImage(w, h, self.view, self.projection, renderer=pb.ER_TINY_RENDERER,
                                physicsClientId=self._client)
        rgb = np.reshape(np.asarray(img[2], dtype=np.uint8), (h, w, 4))[..., :3]
        seg = np.reshape(np.asarray(img[4], dtype=np.int64), (h, w))
        return np.ascontiguousarray(rgb), seg

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (…, 3), sim units → pixels (…, 2) [u right, v down]; NaN stays NaN."""
        p = np.asarray(points, dtype=float)
        homo = np.concatenate([p, np.ones(p.shape[:-1] + (1,))], axis=-1) @ self._pv.T
        ndc = homo[..., :2] / homo[..., 3:4]
        return np.stack([(ndc[..., 0] + 1.0) / 2.0 * self.width,
                         (1.0 - ndc[..., 1]) / 2.0 * self.height], axis=-1)


def _nearest(t_src: np.ndarray, t: float) -> int:
    k = int(np.clip(np.searchsorted(t_src, t), 0, len(t_src) - 1))
    if k > 0 and abs(t_src[k - 1] - t) <= abs(t_src[k] - t):
        k -= 1
    return k


def scene_joints(run, hand_fingers: tuple[int, ...] | None = None) -> tuple[np.ndarray, tuple]:
    """The hand's joint angles (T, 4, 10) from a run's joint states, and which hand finger each
    of the run's fingers is (default: 0.. for four fingers, :data:`GRASPING` for two); the hand's
    other fingers stay straight.

    Raises:
        ValueError: the run has no joint states, or ``hand_fingers`` does not fit it.
    """
    if run.joints is None:
        raise ValueError('the bag has no joint_states: the hand cannot be posed')
    n = run.joints.values.shape[1]
    if hand_fingers is None:
        hand_fingers = GRASPING if n == 2 else tuple(range(n))
    hand_fingers = tuple(int(i) for i in hand_fingers)
    if (len(hand_fingers) != n or len(set(hand_fingers)) != n
            or any(not 0 <= i < len(FINGER_BASE_POSITIONS) for i in hand_fingers)):
        raise ValueError(f'hand fingers {list(hand_fingers)} do not fit the run\'s {n} fingers '
                         f'(one distinct hand finger 0-3 each)')
    q = np.zeros((len(run.joints.t), len(FINGER_BASE_POSITIONS), N_JOINTS))
    q[:, list(hand_fingers)] = run.joints.values[:, :, 0, :]
    return q, hand_fingers


def replay(scene: HandScene, run, times,
           hand_fingers: tuple[int, ...] | None = None) -> list[Frame]:
    """Render ``run`` at each of ``times`` [s] (the joint and cube samples nearest to each).

    Tips and references are those of the run's fingers, in the run's order; a reference is
    drawn at the true tip's height in its finger's base frame (the reference holds X and Y).
    """
    q, hand_fingers = scene_joints(run, hand_fingers)
    frames = []
    for t in times:
        k = _nearest(run.joints.t, t)
        cube = None
        if run.cube_pose is not None:
            cube = run.cube_pose.values[_nearest(run.cube_pose.t, t)]
        scene.set_pose(q[k], cube)
        tips = scene.tips_world()[list(hand_fingers)]
        ref = run.reference.values[_nearest(run.reference.t, t)]          # (n, 4)
        refs = np.full_like(tips, np.nan)
        errors = np.full(len(hand_fingers), np.nan)
        for i, hf in enumerate(hand_fingers):
            if np.all(np.isfinite(ref[i, :2])):
                tip = scene.to_base(hf, tips[i])
                refs[i] = scene.to_world(hf, np.array([ref[i, 0], ref[i, 1], tip[2]]))
                errors[i] = 1e3 * float(np.hypot(*(tip[:2] - ref[i, :2])))
        rgb, seg = scene.render()
        cube_world = scene.cube_world()
        cube_px = None if cube_world is None else scene.project(cube_world)
        frames.append(Frame(float(run.joints.t[k]), rgb, seg, scene.project(tips),
                            scene.project(refs), cube_px, scene.cube, errors))
    return frames


def reference_paths(scene: HandScene, run, hand_fingers: tuple[int, ...] | None = None,
                    every: int = 5) -> np.ndarray:
    """(T', n, 2) pixels of each finger's whole reference path, every ``every``-th tip sample,
    each point at the height of the true tip then."""
    q, hand_fingers = scene_joints(run, hand_fingers)
    idx = np.arange(0, len(run.reference.t), every)
    out = np.full((len(idx), len(hand_fingers), 2), np.nan)
    for row, k in enumerate(idx):
        ref = run.reference.values[k, :, :2]
        scene.set_pose(q[_nearest(run.joints.t, run.reference.t[k])])
        tips = scene.tips_world()
        for i, hf in enumerate(hand_fingers):
            z = scene.to_base(hf, tips[hf])[2]
            out[row, i] = scene.project(scene.to_world(hf, np.array([ref[i, 0], ref[i, 1], z])))
    return out


def visible(frame: Frame, scene: HandScene, hand_fingers) -> np.ndarray:
    """(n,) whether each finger's tip is in sight: the pixel it projects to shows that finger."""
    out = np.zeros(len(hand_fingers), dtype=bool)
    h, w = frame.segmentation.shape
    for i, hf in enumerate(hand_fingers):
        u, v = np.round(frame.tips_px[i]).astype(int)
        if 0 <= u < w and 0 <= v < h:
            out[i] = frame.segmentation[v, u] in (scene.fingers[hf], scene.tip_spheres[hf])
    return out


def blank_fraction(rgb: np.ndarray) -> float:
    """Share of pixels that are the background's colour (the image's most common colour)."""
    flat = rgb.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    return float(counts.max() / len(flat))

