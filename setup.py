"""ament_python build of soft_gripper_sdre (colcon build / pip install)."""
from glob import glob
import re

from setuptools import find_packages, setup

PACKAGE = 'soft_gripper_sdre'


def _version() -> str:
    """The one version string lives in package.xml; setup.py reads it from there."""
    with open('package.xml', encoding='utf-8') as f:
        return re.search(r'<version>([^<]+)</version>', f.read()).group(1)


NODES = {
    'simulator': 'soft_gripper_sdre.nodes.simulator:main',
    'estimator': 'soft_gripper_sdre.nodes.estimator:main',
    'controller': 'soft_gripper_sdre.nodes.controller:main',
    'trajectory': 'soft_gripper_sdre.nodes.trajectory:main',
    'recorder': 'soft_gripper_sdre.nodes.recorder:main',
    'excitation': 'soft_gripper_sdre.nodes.excitation:main',
    'plant_driver': 'soft_gripper_sdre.nodes.plant_driver:main',
    'mocap_tips': 'soft_gripper_sdre.nodes.mocap_tips:main',
}

setup(
    name=PACKAGE,
    version=_version(),
    packages=find_packages(exclude=['test']),
    package_data={PACKAGE: ['models/*.pt', 'models/*.json', 'models/*.npz']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/urdf', glob('urdf/*.urdf')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='soft_gripper_sdre maintainers',
    maintainer_email='maintainers@soft-gripper-sdre.invalid',
    description='Learned-model SDRE tracking control of a soft gripper as a ROS 2 node graph',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{name} = {target}' for name, target in NODES.items()]
        + [
            'sgs_echo = soft_gripper_sdre.tools.graph.echo:main',
        ],
    },
)
