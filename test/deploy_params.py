"""A params.yaml as training writes it, for the deploy tool's tests and the README recipe's
(shared; no test imports another)."""
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / 'soft_gripper_sdre' / 'models' / 'default.pt'
NAMES = ['index', 'thumb']


def params_file(path: Path, drop: tuple[str, ...] = (), **plan) -> Path:
    """A params.yaml as training writes it, for the package's model on two fingers of tendon3
    (200 Hz, ±0.02 N·m), with a short plan."""
    trajectory = {'finger_names': list(NAMES), 'grasp_fingers': [0, 1], 'others': 'hold',
                  't_start': 0.5, 't_close': 1.0, 't_hold': 0.5, 't_open': 1.0,
                  'close_distance': 0.002, 'side_distance': 0.0, 'contact_distance': 0.002,
                  'rest_samples': 50, **plan}
    for key in drop:
        trajectory.pop(key)
    body = {'/**/estimator': {'ros__parameters': {'finger_names': list(NAMES),
                                                  'control_period': 0.005}},
            '/**/controller': {'ros__parameters': {'model_path': str(MODEL),
                                                   'finger_names': list(NAMES),
                                                   'control_period': 0.005,
                                                   'torque_limit': 0.02}},
            '/**/trajectory': {'ros__parameters': trajectory}}
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    return path
