"""The hand's robot description (URDF, SI) and its forward kinematics, for viewers (no ROS).

:func:`hand_urdf` writes one URDF of the whole hand from the simulator's own finger
(:func:`soft_gripper_sdre.sim.finger.finger_urdf`, parsed, not retyped) and hand layout: a root
link ``hand`` carrying the palm, one fixed ``<finger>/mount`` joint per finger at its base pose,
and each finger's chain with links ``<finger>/base``, ``<finger>/link_<j>`` and revolute
joints ``<finger>/joint_<j>``, the names the simulator's ``joint_states`` carry. Lengths are
converted from SoMo's scaled world to metres, inertias to kg·m², effort limits to N·m. Every
collision shape also gets a visual (the simulator's fingertip sphere has none), so a viewer
shows what touches the cube. ``python -m soft_gripper_sdre.sim.hand_description`` prints it
(the installed ``urdf/hand.urdf``).

:class:`HandKinematics` parses such a URDF and gives every visual's pose in the ``hand`` frame for
given joint angles: what the live markers draw.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
import xml.etree.ElementTree as ET

import numpy as np

from soft_gripper_sdre import FINGER_NAMES
from soft_gripper_sdre.sim.finger import (
    FINGER_BASE_POSITIONS,
    N_JOINTS,
    PALM,
    TIP_LINK,
    finger_base_rpy,
    finger_urdf,
)
from soft_gripper_sdre.sim.units import LENGTH_SCALE, TORQUE_SCALE

ROOT = 'hand'
#: the file under the package's share/ directory (setup.py installs urdf/*.urdf there)
URDF_FILE = 'urdf/hand.urdf'


def _scaled(text: str, factor: float) -> str:
    return ' '.join(f'{float(v) * factor:.9g}' for v in text.split())


def joint_name(finger: str, j: int) -> str:
    return f'{finger}/joint_{j}'


def link_name(finger: str, j: int) -> str:
    return f'{finger}/link_{j}'


def _finger_elements(name: str) -> list[ET.Element]:
    """The simulator's finger URDF, renamed for finger ``name`` and converted to SI."""
    robot = ET.fromstring(finger_urdf())
    rename = {'base': f'{name}/base'}
    rename.update({f'link{j}': link_name(name, j) for j in range(N_JOINTS)})
    out = []
    for el in robot:
        if el.tag == 'link':
            el.set('name', rename[el.get('name')])
            for origin in el.iter('origin'):
                origin.set('xyz', _scaled(origin.get('xyz'), 1 / LENGTH_SCALE))
            for box in el.iter('box'):
                box.set('size', _scaled(box.get('size'), 1 / LENGTH_SCALE))
            for sphere in el.iter('sphere'):
                sphere.set('radius', _scaled(sphere.get('radius'), 1 / LENGTH_SCALE))
            for inertia in el.iter('inertia'):
                for key, value in inertia.attrib.items():
                    inertia.set(key, _scaled(value, 1 / LENGTH_SCALE**2))
            visuals = {ET.tostring(v.find('geometry')) for v in el.findall('visual')}
            for collision in el.findall('collision'):
                if ET.tostring(collision.find('geometry')) not in visuals:
                    visual = ET.SubElement(el, 'visual')
                    visual.extend(list(collision))
        else:
            j = int(el.get('name').removeprefix('joint'))
            el.set('name', joint_name(name, j))
            el.find('parent').set('link', rename[el.find('parent').get('link')])
            el.find('child').set('link', rename[el.find('child').get('link')])
            origin = el.find('origin')
            origin.set('xyz', _scaled(origin.get('xyz'), 1 / LENGTH_SCALE))
            limit = el.find('limit')
            limit.set('effort', f'{float(limit.get("effort")) / TORQUE_SCALE:.9g}')
        out.append(el)
    return out


def hand_urdf(finger_names=FINGER_NAMES, hand_fingers=None) -> str:
    """URDF of the hand whose fingers ``hand_fingers`` (default 0, 1, … of the hand) are named
    ``finger_names`` (the simulator's parameters of the same names); SI units."""
    names = list(finger_names)
    if hand_fingers is None:
        hand_fingers = range(len(names))
    hand_fingers = [int(i) for i in hand_fingers]
    if len(hand_fingers) != len(names):
        raise ValueError(f'{len(names)} finger names but {len(hand_fingers)} hand fingers')
    robot = ET.Element('robot', name='soft_gripper_hand')
    hand = ET.SubElement(robot, 'link', name=ROOT)
    palm = ET.SubElement(hand, 'visual')
    centre = ' '.join(f'{c / LENGTH_SCALE:.9g}' for c in PALM['center'])
    ET.SubElement(palm, 'origin', xyz=centre, rpy='0 0 0')
    geometry = ET.SubElement(palm, 'geometry')
    ET.SubElement(geometry, 'cylinder', radius=f'{PALM["radius"] / LENGTH_SCALE:.9g}',
                  length=f'{PALM["length"] / LENGTH_SCALE:.9g}')
    collision = ET.SubElement(hand, 'collision')
    collision.extend(list(palm))
    for name, i in zip(names, hand_fingers):
        robot.extend(_finger_elements(name))
        mount = ET.SubElement(robot, 'joint', name=f'{name}/mount', type='fixed')
        ET.SubElement(mount, 'parent', link=ROOT)
        ET.SubElement(mount, 'child', link=f'{name}/base')
        xyz = ' '.join(f'{c / LENGTH_SCALE:.9g}' for c in FINGER_BASE_POSITIONS[i])
        rpy = ' '.join(f'{a:.9g}' for a in finger_base_rpy(i))
        ET.SubElement(mount, 'origin', xyz=xyz, rpy=rpy)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding='unicode') + '\n'


# -- forward kinematics ------------------------------------------------------------------------

def _vector(text: str | None) -> np.ndarray:
    return np.array([float(v) for v in (text or '0 0 0').split()])


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
    cy, sy = math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _origin(el: ET.Element | None) -> np.ndarray:
    """4x4 transform of an ``<origin>`` element (identity if absent)."""
    T = np.eye(4)
    if el is not None:
        T[:3, :3] = _rpy_matrix(_vector(el.get('rpy')))
        T[:3, 3] = _vector(el.get('xyz'))
    return T


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """4x4 rotation by ``angle`` about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    T = np.eye(4)
    T[:3, :3] = [[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                 [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                 [z * x * C - y * s, z * y * C + x * s, c + z * z * C]]
    return T


@dataclass(frozen=True)
class Visual:
    """One visual of a link: ``kind`` 'box' (size: 3 edges), 'sphere' (size: diameter ×3) or
    'cylinder' (size: diameter, diameter, length), its pose in the link frame."""

    link: str
    kind: str
    size: tuple[float, float, float]
    origin: np.ndarray        # 4x4


class HandKinematics:
    """Forward kinematics of a URDF tree (fixed and revolute joints) from its root.

    Args:
        urdf: URDF text, e.g. :func:`hand_urdf`.
    """

    def __init__(self, urdf: str) -> None:
        robot = ET.fromstring(urdf)
        self.links = [el.get('name') for el in robot.findall('link')]
        children = {el.find('child').get('link') for el in robot.findall('joint')}
        roots = [name for name in self.links if name not in children]
        if len(roots) != 1:
            raise ValueError(f'the URDF must have one root link, it has {roots}')
        self.root = roots[0]
        by_parent: dict[str, list[ET.Element]] = {}
        for el in robot.findall('joint'):
            by_parent.setdefault(el.find('parent').get('link'), []).append(el)
        # joints depth first in file order: every parent before its children
        self._chain = []

        def visit(parent: str) -> None:
            for el in by_parent.get(parent, []):
                child = el.find('child').get('link')
                axis = _vector(el.find('axis').get('xyz')) if el.find('axis') is not None else None
                turned = None
                if axis is not None and np.count_nonzero(axis) == 1 and abs(axis.sum()) == 1.0:
                    i = int(np.flatnonzero(axis)[0])
                    turned = ((i + 1) % 3, (i + 2) % 3, float(axis[i]))
                self._chain.append((el.get('name'), el.get('type'), parent, child,
                                    _origin(el.find('origin')), axis, turned))
                visit(child)

        visit(self.root)
        self.joint_names = [name for name, kind, *_ in self._chain if kind != 'fixed']
        #: each link's centre of mass in its own frame (links with an ``<inertial>``)
        self.com = {el.get('name'): _vector(el.find('inertial/origin').get('xyz'))
                    for el in robot.findall('link') if el.find('inertial/origin') is not None}
        self.visuals = []
        for el in robot.findall('link'):
            for visual in el.findall('visual'):
                geometry = visual.find('geometry')[0]
                if geometry.tag == 'box':
                    size = tuple(_vector(geometry.get('size')))
                elif geometry.tag == 'sphere':
                    size = (2 * float(geometry.get('radius')),) * 3
                elif geometry.tag == 'cylinder':
                    d = 2 * float(geometry.get('radius'))
                    size = (d, d, float(geometry.get('length')))
                else:
                    continue
                self.visuals.append(Visual(el.get('name'), geometry.tag, size,
                                           _origin(visual.find('origin'))))
        self._visual_origins = np.stack([v.origin for v in self.visuals])

    def link_poses(self, positions: dict[str, float]) -> dict[str, np.ndarray]:
        """Each link's 4x4 pose in the root frame for joint angles ``positions`` (by joint name;
        missing joints at 0)."""
        poses = {self.root: np.eye(4)}
        for name, kind, parent, child, origin, axis, turned in self._chain:
            T = poses[parent] @ origin
            if kind != 'fixed':
                angle = positions.get(name, 0.0)
                if turned is not None:            # about a frame axis: two columns turn
                    a, b, sign = turned
                    c, s = math.cos(angle), sign * math.sin(angle)
                    col_a = T[:3, a] * c + T[:3, b] * s
                    T[:3, b] = T[:3, b] * c - T[:3, a] * s
                    T[:3, a] = col_a
                else:
                    T = T @ _axis_rotation(axis, angle)
            poses[child] = T
        return poses

    def visual_poses(self, positions: dict[str, float]) -> np.ndarray:
        """(V, 4, 4) the pose of each of :attr:`visuals` in the root frame."""
        links = self.link_poses(positions)
        return np.stack([links[v.link] for v in self.visuals]) @ self._visual_origins


def tip_link(finger: str) -> str:
    """The link whose centre of mass is finger ``finger``'s controlled point."""
    return link_name(finger, TIP_LINK)


if __name__ == '__main__':
    print(hand_urdf(), end='')
