"""The hand as ``visualization_msgs/MarkerArray`` for RViz and Foxglove, as ready CDR bytes.

:class:`HandMarkers` lays one MarkerArray out once (every visual of the hand's URDF, the cube, the
true tips and, optionally, the references), serialised with rosbags' Jazzy types, and learns
where each pose, point and stamp sits in its bytes. :meth:`HandMarkers.encode` then writes the new
values into that buffer with numpy: no message object is built or converted per update (rclpy
takes about 15 ms to convert this array of 50-odd markers, the encoding about 0.5 ms). A
publisher of the MarkerArray type publishes the bytes as they are. Poses come from the URDF's
forward kinematics (:class:`~soft_gripper_sdre.sim.hand_description.HandKinematics`), so the
markers and a ``robot_state_publisher`` fed the same ``joint_states`` draw the same hand. Every
marker is in the ``hand`` frame; a viewer needs no TF to show them.

Namespaces: ``links`` (one CUBE / SPHERE / CYLINDER per visual, the palm included), ``cube``,
``tips`` (a SPHERE_LIST, one point per finger: the controlled point, link 9's centre of mass) and
``references`` (a SPHERE_LIST of each finger's reference at its tip's height).

No rclpy here: the bytes are built and checked with rosbags alone.
"""
from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np
from rosbags.typesys import Stores, get_typestore

from soft_gripper_sdre.sim.finger import CUBE
from soft_gripper_sdre.sim.hand_description import ROOT, HandKinematics, joint_name, tip_link
from soft_gripper_sdre.sim.units import LENGTH_SCALE

MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
STORE = get_typestore(Stores.ROS2_JAZZY)
_T = STORE.types
_NS = 1_000_000_000
#: the template's stamp, found at every marker's header
_SENTINEL_STAMP = struct.pack('<iI', 0x5A5A_1234, 0x3B9A_C9FF)
#: the fingers that grasp the cube are drawn blue, the others grey
GRASPING = (0, 2)
_COLOURS = {'grasping': (0.33, 0.55, 0.85, 1.0), 'other': (0.78, 0.78, 0.80, 1.0),
            'base': (0.35, 0.35, 0.38, 1.0), 'palm': (0.45, 0.45, 0.48, 1.0),
            'cube': (0.0, 0.75, 0.0, 1.0), 'tips': (1.0, 0.8, 0.0, 1.0),
            'references': (0.85, 0.1, 0.1, 0.8)}
_KINDS = {'box': 1, 'sphere': 2, 'cylinder': 3}          # Marker.CUBE, SPHERE, CYLINDER
SPHERE_LIST, CUBE_KIND, ADD = 7, 1, 0
#: diameter of the tip and reference spheres [m]
TIP_DIAMETER, REFERENCE_DIAMETER = 0.004, 0.006


def quaternions(R: np.ndarray) -> np.ndarray:
    """(…, 4) unit quaternions [x, y, z, w] of rotation matrices (…, 3, 3)."""
    d0, d1, d2 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    w = np.sqrt(np.maximum(0.0, 1.0 + d0 + d1 + d2)) / 2
    x = np.copysign(np.sqrt(np.maximum(0.0, 1.0 + d0 - d1 - d2)) / 2, R[..., 2, 1] - R[..., 1, 2])
    y = np.copysign(np.sqrt(np.maximum(0.0, 1.0 - d0 + d1 - d2)) / 2, R[..., 0, 2] - R[..., 2, 0])
    z = np.copysign(np.sqrt(np.maximum(0.0, 1.0 - d0 - d1 + d2)) / 2, R[..., 1, 0] - R[..., 0, 1])
    return np.stack([x, y, z, w], axis=-1)


class _Sentinels:
    """Distinct float64s to mark the template's moving fields."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def take(self, count: int) -> list[float]:
        start = len(self.values)
        self.values += [-1234.5 - (start + k) * 0.0078125 * np.pi for k in range(count)]
        return self.values[start:]


def _vec3(cls: str, xyz) -> object:
    return _T[cls](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _find_all(raw: bytes, pattern: bytes, expected: int) -> list[int]:
    """Every offset of ``pattern`` in ``raw``; there must be ``expected`` of them."""
    found, at = [], raw.find(pattern)
    while at >= 0:
        found.append(at)
        at = raw.find(pattern, at + 1)
    if len(found) != expected:
        raise ValueError(f'MarkerArray template: a sentinel occurs {len(found)} times, '
                         f'expected {expected}')
    return found


def _offsets(raw: bytes, values) -> np.ndarray:
    """The byte offset of each float64 sentinel of ``values`` in ``raw`` (each occurs once)."""
    found = []
    for v in values:
        (at,) = _find_all(raw, struct.pack('<d', v), 1)
        found.append(at)
    return np.array(found, dtype=np.intp).reshape(-1)


def _colour(link: str, grasping: set[str]) -> str:
    """A link's colour: the palm's, a finger base's, or its finger's (grasping or not)."""
    if link == ROOT:
        return 'palm'
    if link.endswith('/base'):
        return 'base'
    return 'grasping' if link.split('/')[0] in grasping else 'other'


class _Slots(NamedTuple):
    """The sentinels standing for the template's moving fields, by namespace."""

    links: list[list[float]]        # per visual: position, orientation [x, y, z, w]
    cube: list[float]               # its pose, or none without the cube
    tips: list[float]               # x, y, z per finger
    references: list[float]         # x, y, z per finger, or none without references


class HandMarkers:
    """The hand's MarkerArray as CDR bytes, laid out once, rewritten per update.

    Args:
        urdf: the hand's URDF (:func:`~soft_gripper_sdre.sim.hand_description.hand_urdf` with
            the same finger names).
        finger_names: the fingers whose joint angles :meth:`encode` gets, in that order.
        hand_fingers: which of the hand's fingers each of them is (colours: 0 and 2 grasp).
        with_cube, with_references: draw the cube, the references.
    """

    def __init__(self, urdf: str, finger_names, hand_fingers, with_cube: bool = True,
                 with_references: bool = False) -> None:
        self.kin = HandKinematics(urdf)
        self.names = list(finger_names)
        self._joint_names = [[joint_name(n, j) for j in range(10)] for n in self.names]
        self.with_cube, self.with_references = with_cube, with_references
        markers, slots = self._layout({n for n, i in zip(self.names, hand_fingers)
                                       if int(i) in GRASPING})
        self.count = len(markers)
        # serialised once with sentinels in the moving fields: where they land, encode writes
        raw = bytes(STORE.serialize_cdr(_T[MARKER_ARRAY](markers=markers), MARKER_ARRAY))
        self._stamps = _find_all(raw, _SENTINEL_STAMP, self.count)
        n = len(self.names)
        self._link_at = _offsets(raw, [v for pose in slots.links for v in pose]).reshape(-1, 7)
        self._cube_at = _offsets(raw, slots.cube)
        self._tip_at = _offsets(raw, slots.tips).reshape(n, 3)
        self._ref_at = _offsets(raw, slots.references).reshape(-1, 3)
        self._buf = bytearray(raw)
        self._words = np.frombuffer(self._buf, np.uint8)
        self._write_rest(len(slots.links))
        self._tip_com = [self.kin.com[tip_link(n)] for n in self.names]
        self._visual_origins = np.stack([v.origin for v in self.kin.visuals])
        self.stamp(0)

    def _layout(self, grasping: set[str]) -> tuple[list, _Slots]:
        """The markers, each moving field a sentinel, in namespace order: links, cube, tips,
        references (``grasping``: the fingers drawn in the grasping colour)."""
        marks = _Sentinels()
        markers = []
        link_slots = []
        for k, visual in enumerate(self.kin.visuals):
            pose = marks.take(7)
            link_slots.append(pose)
            markers.append(self._marker('links', k, _KINDS[visual.kind],
                                        _colour(visual.link, grasping), visual.size, pose))
        cube_slots = []
        if self.with_cube:
            cube_slots = marks.take(7)
            markers.append(self._marker('cube', 0, CUBE_KIND, 'cube',
                                        (CUBE['size'] / LENGTH_SCALE,) * 3, cube_slots))
        n = len(self.names)
        tip_slots = marks.take(3 * n)
        markers.append(self._marker('tips', 0, SPHERE_LIST, 'tips', (TIP_DIAMETER,) * 3,
                                    None, tip_slots))
        ref_slots = []
        if self.with_references:
            ref_slots = marks.take(3 * n)
            markers.append(self._marker('references', 0, SPHERE_LIST, 'references',
                                        (REFERENCE_DIAMETER,) * 3, None, ref_slots))
        return markers, _Slots(link_slots, cube_slots, tip_slots, ref_slots)

    def _write_rest(self, links: int) -> None:
        """A valid message before the first update: identity orientations, everything at 0."""
        rest = np.zeros((links, 7))
        rest[:, 6] = 1.0
        self._write(self._link_at, rest)
        if self.with_cube:
            self._write(self._cube_at, np.array([0, 0, 0, 0, 0, 0, 1.0]))
        self._write(self._tip_at, np.zeros((len(self.names), 3)))
        if self.with_references:
            self._write(self._ref_at, np.zeros((len(self.names), 3)))

    @staticmethod
    def _marker(ns: str, marker_id: int, kind: int, colour: str, size, pose=None, points=()):
        r, g, b, a = _COLOURS[colour]
        sec, nanosec = struct.unpack('<iI', _SENTINEL_STAMP)
        header = _T['std_msgs/msg/Header'](
            stamp=_T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=ROOT)
        pose = pose or (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        return _T['visualization_msgs/msg/Marker'](
            header=header, ns=ns, id=marker_id, type=kind, action=ADD,
            pose=_T['geometry_msgs/msg/Pose'](
                position=_vec3('geometry_msgs/msg/Point', pose[:3]),
                orientation=_T['geometry_msgs/msg/Quaternion'](x=pose[3], y=pose[4], z=pose[5],
                                                               w=pose[6])),
            scale=_vec3('geometry_msgs/msg/Vector3', size),
            color=_T['std_msgs/msg/ColorRGBA'](r=r, g=g, b=b, a=a),
            lifetime=_T['builtin_interfaces/msg/Duration'](sec=0, nanosec=0), frame_locked=False,
            points=[_vec3('geometry_msgs/msg/Point', points[3 * k:3 * k + 3])
                    for k in range(len(points) // 3)],
            colors=[], texture_resource='',
            texture=_T['sensor_msgs/msg/CompressedImage'](
                header=_T['std_msgs/msg/Header'](
                    stamp=_T['builtin_interfaces/msg/Time'](sec=0, nanosec=0), frame_id=''),
                format='', data=np.empty(0, dtype=np.uint8)),
            uv_coordinates=[], text='',
            mesh_resource='', mesh_file=_T['visualization_msgs/msg/MeshFile'](
                filename='', data=np.empty(0, dtype=np.uint8)),
            mesh_use_embedded_materials=False)

    def _write(self, at: np.ndarray, values) -> None:
        """float64 ``values`` at byte offsets ``at`` (same shape)."""
        data = np.asarray(values, dtype='<f8').reshape(-1)
        idx = at.reshape(-1)[:, None] + np.arange(8)
        self._words[idx] = data.view(np.uint8).reshape(-1, 8)

    def stamp(self, ns: int) -> None:
        sec_nanosec = struct.pack('<iI', *divmod(int(ns), _NS))
        for at in self._stamps:
            self._buf[at:at + 8] = sec_nanosec

    def encode(self, ns: int, q: np.ndarray, cube_pose: np.ndarray | None = None,
               references: np.ndarray | None = None) -> bytes:
        """The MarkerArray's CDR bytes at sim time ``ns`` [ns] for joint angles ``q`` (n, 10)
        [rad] of the fingers, the cube's pose [x, y, z (m), qx, qy, qz, qw] and the references
        (n, 2) or (n, 3) [m] in each finger's base frame (a non-finite row keeps its last value;
        a planar reference is drawn at its tip's height in the base frame, a 3-D one at its z)."""
        positions = {name: angle for names, row in zip(self._joint_names, np.asarray(q).tolist())
                     for name, angle in zip(names, row)}
        links = self.kin.link_poses(positions)
        visuals = np.stack([links[v.link] for v in self.kin.visuals]) @ self._visual_origins
        self._write(self._link_at, np.concatenate([visuals[:, :3, 3],
                                                   quaternions(visuals[:, :3, :3])], axis=1))
        tips = np.array([links[tip_link(name)][:3, :3] @ com + links[tip_link(name)][:3, 3]
                         for name, com in zip(self.names, self._tip_com)])
        self._write(self._tip_at, tips)
        if self.with_references and references is not None:
            refs = np.asarray(references, dtype=float)
            for i, name in enumerate(self.names):
                if not np.all(np.isfinite(refs[i])):
                    continue
                R, p0 = links[f'{name}/base'][:3, :3], links[f'{name}/base'][:3, 3]
                z = (R.T @ (tips[i] - p0))[2] if refs.shape[1] == 2 else refs[i, 2]
                self._write(self._ref_at[i], R @ [refs[i, 0], refs[i, 1], z] + p0)
        if self.with_cube and cube_pose is not None:
            self._write(self._cube_at, np.asarray(cube_pose, dtype=float)[:7])
        self.stamp(ns)
        return bytes(self._buf)


def decode(data: bytes):
    """A MarkerArray's CDR bytes as rosbags' message object (for tests and tools)."""
    return STORE.deserialize_cdr(data, MARKER_ARRAY)
