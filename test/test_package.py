"""Package hygiene: ROS stays at the edge, one version string, config files parse, colcon build."""
import ast
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / 'soft_gripper_sdre'
#: subpackages bottom to top: a module may import from its own layer and the layers before it
LAYERS = (('sim', 'learning'), ('control',), ('analysis',), ('nodes', 'tools'))
CORE_LAYERS = ('sim', 'learning', 'control', 'analysis')
CORE_MODULES = sorted(p for layer in CORE_LAYERS for p in (PKG / layer).rglob('*.py'))
ALL_MODULES = sorted(PKG.rglob('*.py'))
TEST_MODULES = sorted((ROOT / 'test').glob('test_*.py'))
ROS_PREFIXES = ('rclpy', 'rosidl', 'rosgraph_msgs', 'builtin_interfaces')
NODES = ('simulator', 'estimator', 'controller', 'trajectory', 'recorder', 'excitation',
         'plant_driver', 'mocap_tips')


def _imported_modules(path: Path) -> list[tuple[str, tuple[str, ...]]]:
    """(module, names) of every absolute import in the file; names are empty for ``import m``."""
    tree = ast.parse(path.read_text(encoding='utf-8'))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, ()) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, tuple(a.name for a in node.names)))
    return out


def _imports(path: Path) -> set[str]:
    return {module.split('.')[0] for module, _ in _imported_modules(path)}


def _rel(path: Path) -> str:
    return path.relative_to(PKG).as_posix()


def _layer(subpackage: str) -> int | None:
    return next((i for i, names in enumerate(LAYERS) if subpackage in names), None)


@pytest.mark.parametrize('path', CORE_MODULES, ids=_rel)
def test_core_module_imports_no_ros(path):
    bad = {n for n in _imports(path) if n.startswith(ROS_PREFIXES) or n.endswith('_msgs')}
    assert not bad, f'{_rel(path)} is a core module but imports {sorted(bad)}'


@pytest.mark.parametrize('path', ALL_MODULES, ids=_rel)
def test_torch_is_imported_by_the_learning_package_alone(path):
    if _rel(path).startswith('learning/'):
        return
    assert 'torch' not in _imports(path), (
        f'{_rel(path)}: torch belongs to soft_gripper_sdre.learning')


@pytest.mark.parametrize('path', ALL_MODULES, ids=_rel)
def test_imports_run_down_the_layers(path):
    """sim and learning at the bottom, then control, analysis, and nodes and tools on top."""
    parts = path.relative_to(PKG).parts
    own = _layer(parts[0]) if len(parts) > 1 else -1          # the package's __init__: below all
    for module, names in _imported_modules(path):
        if not module.startswith(f'{PKG.name}.'):
            continue
        target = module.split('.')[1]
        layer = _layer(target)
        if layer is None:                                     # the top-level package itself
            continue
        assert own is not None and own >= 0 and layer <= own, (
            f'{_rel(path)} imports {module}: {target} is above {parts[0]} in {LAYERS}')


@pytest.mark.parametrize('path', ALL_MODULES, ids=_rel)
def test_no_module_imports_another_modules_private_names(path):
    for module, names in _imported_modules(path):
        if module.startswith(PKG.name):
            private = [n for n in names if n.startswith('_') and not n.startswith('__')]
            assert not private, f'{_rel(path)} imports private {private} from {module}'


@pytest.mark.parametrize('path', TEST_MODULES, ids=lambda p: p.name)
def test_no_test_module_imports_another(path):
    """A test module is a leaf: what several of them share lives in conftest.py (fixtures) or in a
    helper module whose name does not start with ``test_``, so no test file depends on another's."""
    tests = [module for module, _ in _imported_modules(path)
             if module.split('.')[0].startswith('test_')]
    assert not tests, f'{path.name} imports the test module(s) {tests}'


def test_one_version_string():
    xml_version = re.search(r'<version>([^<]+)</version>',
                            (ROOT / 'package.xml').read_text()).group(1)
    assert 'version=' not in (ROOT / 'setup.py').read_text().replace('version=_version()', '')
    from soft_gripper_sdre import __version__
    assert __version__ == xml_version


@pytest.mark.parametrize('path', sorted((ROOT / 'config').glob('*.yaml')), ids=lambda p: p.name)
def test_config_files_are_ros_params_files(path):
    doc = yaml.safe_load(path.read_text())
    assert isinstance(doc, dict) and doc
    for node_name, section in doc.items():
        assert set(section) == {'ros__parameters'}, (
            f'{path.name}: {node_name} must hold only ros__parameters')


@pytest.mark.slow
def test_colcon_build_installs_every_node(tmp_path):
    colcon = Path(sys.executable).parent / 'colcon'
    if not colcon.exists():
        pytest.fail('colcon is not installed in the venv (requirements.txt pins '
                    'colcon-common-extensions)')
    src = tmp_path / 'ws' / 'src' / 'soft_gripper_sdre'
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', 'runs', 'data', '*.egg-info', '__pycache__'))
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE='1')
    proc = subprocess.run([str(colcon), 'build', '--base-paths', 'src'], cwd=tmp_path / 'ws',
                          env=env, capture_output=True, text=True, timeout=50)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    install = tmp_path / 'ws' / 'install' / 'soft_gripper_sdre'
    for node in NODES:
        exe = install / 'lib' / 'soft_gripper_sdre' / node
        assert exe.is_file() and os.access(exe, os.X_OK), (
            f'{exe} missing: ros2 run would not find {node}')
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages'
            / 'soft_gripper_sdre').is_file()
    assert (install / 'share' / 'soft_gripper_sdre' / 'package.xml').is_file()
    assert list((install / 'share' / 'soft_gripper_sdre' / 'config').glob('*.yaml'))
    assert (install / 'share' / 'soft_gripper_sdre' / 'launch' / 'grasp.launch.py').is_file(), \
        'ros2 launch soft_gripper_sdre grasp.launch.py would not find the launch file'


@pytest.mark.parametrize('node', NODES)
def test_config_file_holds_every_declared_default(node):
    """config/<node>.yaml is exactly the node's declared parameters with their defaults."""
    import importlib

    from soft_gripper_sdre.nodes.params import to_yaml
    module = importlib.import_module(f'soft_gripper_sdre.nodes.{node}')
    assert yaml.safe_load((ROOT / 'config' / f'{node}.yaml').read_text()) == \
        yaml.safe_load(to_yaml(node, module.PARAMS))


def test_lost_commands_are_stepped_sooner_than_the_first_timeout_waits():
    """Once a lockstep timeout has found the commands lost, each further period waits only
    lost_command_wait before it steps with zero torque; the shipped defaults keep that wait well
    below lockstep_timeout, so a dead estimator or controller is not waited out period by period."""
    def default(node, name):
        doc = yaml.safe_load((ROOT / 'config' / f'{node}.yaml').read_text())
        return next(iter(doc.values()))['ros__parameters'][name]
    assert (10 * default('simulator', 'lost_command_wait')
            <= default('simulator', 'lockstep_timeout'))


def test_package_xml_declares_every_ros_package_the_code_imports():
    """A rosdep/colcon user gets every ROS package the nodes import from package.xml alone."""
    declared = set(re.findall(r'<exec_depend>([^<]+)</exec_depend>',
                              (ROOT / 'package.xml').read_text()))
    ros_like = ('rclpy', 'rcl_interfaces', 'ament_index_python', 'builtin_interfaces',
                'rosgraph_msgs')
    imported = {name for path in ALL_MODULES for name in _imports(path)
                if name in ros_like or name.endswith('_msgs')}
    assert imported, 'the nodes import ROS packages; the scan found none'
    assert imported <= declared, f'package.xml lacks exec_depend for {sorted(imported - declared)}'


def test_parameter_reference_is_generated_from_the_declarations():
    """docs/parameters.md is what tools/params_doc renders from the nodes' PARAMS (regenerate with
    ``python -m soft_gripper_sdre.tools.params_doc``)."""
    from soft_gripper_sdre.tools.params_doc import render
    assert (ROOT / 'docs' / 'parameters.md').read_text(encoding='utf-8') == render()
