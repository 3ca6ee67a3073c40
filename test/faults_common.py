"""What the fault-injection tests share: tracking error, recovery time, and the outcome records.

Each fault test writes one JSON record of what it measured to the directory ``$FAULTS_OUT``,
which test/conftest.py sets to a fresh temporary directory for the session unless it is set
already. To keep the records, name a directory: ``FAULTS_OUT=runs/faults pytest test/test_faults.py
test/test_faults_procs.py test/test_fuzz.py``; ``python test/faults_common.py runs/faults`` then
renders them as the README table "Faults survived".
"""
from __future__ import annotations

import json
import os
from pathlib import Path
import sys

import numpy as np

from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory

#: the free-space tracking target: RMSE <= 5 % of each finger's peak excursion
TARGET_PCT = 5.0
#: window of the moving RMSE that decides whether tracking is back [s]
WINDOW = 0.1
#: the number of each fault in the README table "Faults survived", and the table's row order
ITEMS = {'fuzz_simulator': 1, 'fuzz_estimator': 1, 'fuzz_trajectory': 1, 'fuzz_controller': 1,
         'fuzz_trajectory_clock': 1, 'fuzz_controller_d2m1': 1, 'fuzz_controller_d3m3': 1,
         'fuzz_composed_d2m1': 1, 'fuzz_composed_d3m3': 1, 'fuzz_estimator_3d': 1,
         'fuzz_plant_driver_pneumatic1': 1, 'fuzz_plant_driver_trunk3': 1, 'fuzz_mocap_tips': 1,
         'fuzz_excitation_m1': 1, 'fuzz_excitation_m3': 1, 'fuzz_recorder': 1,
         'fuzz_simulator_two_fingers': 1, 'lost_estimates': 2,
         'crashed_controller': 3,
         'crashed_estimator': 4, 'crashed_trajectory': 4, 'riccati_trouble': 5, 'recording': 8,
         'clock_jump_back': 9, 'link_down': 10}
#: environment variable naming the directory of the outcome records
RECORDS_ENV = 'FAULTS_OUT'


def tracking_error(t: np.ndarray, tips: np.ndarray, contact: np.ndarray, profile: GraspProfile,
                   rest: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Free-space tip error of every finger.

    Free space here is every sample where the finger does not touch the cube (there its error is
    the squeeze). Unlike the tracking score of the demo, the reference's contact phases are not
    left out: a finger that should be pressing on the cube but has sprung back is scored.

    Args:
        t: (T,) sim time [s]; tips: (T, n, 2) measured tips [m]; contact: (T, n) bool, touching
            the cube; profile, rest: the grasp the trajectory node runs (rest = its first tips).

    Returns:
        err (T, n) [m] ‖p − p_d‖, free (T, n) bool, excursion (n,) [m].
    """
    traj = GraspTrajectory(rest, profile)
    ref = traj.sample(t).pos
    free = ~contact
    return np.linalg.norm(tips - ref, axis=2), free, traj.peak_excursion()


def on_target(t: np.ndarray, err: np.ndarray, free: np.ndarray, excursion: np.ndarray,
              window: float = WINDOW,
              target_pct: float = TARGET_PCT) -> tuple[np.ndarray, np.ndarray]:
    """Whether every finger's moving free-space RMSE (over ``window``) is under ``target_pct`` %
    of its excursion: (window end times, bool) per sample from the first full window on.

    A window with no free-space sample of a finger (it touches the cube) does not hold it back,
    nor does a finger whose reference does not move (no excursion to score against).
    """
    dt = float(np.median(np.diff(t)))
    w = max(1, int(round(window / dt)))
    e2 = np.where(free, err, 0.0) ** 2
    c = np.concatenate([np.zeros((1, err.shape[1])), np.cumsum(e2, axis=0)])
    n = np.concatenate([np.zeros((1, err.shape[1])), np.cumsum(free, axis=0)])
    s, m = c[w:] - c[:-w], n[w:] - n[:-w]                  # sums over samples k-w+1 … k
    rmse = np.sqrt(np.divide(s, m, out=np.zeros_like(s), where=m > 0))
    moving = excursion > 0
    return t[w - 1:], np.all(rmse[:, moving] <= target_pct / 100 * excursion[moving], axis=1)


def recovery_time(t: np.ndarray, err: np.ndarray, free: np.ndarray, excursion: np.ndarray,
                  since: float, **kwargs) -> float:
    """Sim time after ``since`` until tracking is :func:`on_target` and stays there to the end;
    inf if it never is."""
    ends, ok = on_target(t, err, free, excursion, **kwargs)
    bad = np.flatnonzero(~ok & (ends >= since))
    if bad.size == 0:
        return 0.0
    if bad[-1] == len(ok) - 1:
        return float('inf')
    return float(ends[bad[-1] + 1] - since)


def hostile_value(rng: np.random.Generator, spread: float) -> float:
    """One seeded fuzz number: NaN (4 %), ±Inf (2 %), ±1e300, 0 or a subnormal (4 %), else
    normal with standard deviation ``spread`` (the fuzz tests' shared draw)."""
    r = rng.random()
    if r < 0.04:
        return float('nan')
    if r < 0.06:
        return float(rng.choice([np.inf, -np.inf]))
    if r < 0.1:
        return float(rng.choice([1e300, -1e300, 0.0, 5e-324]))
    return float(rng.normal(0.0, spread))


def records_dir() -> Path:
    """The directory named by ``$FAULTS_OUT``.

    Raises:
        RuntimeError: the variable is not set (outside pytest, which sets it in conftest.py).
    """
    directory = os.environ.get(RECORDS_ENV)
    if not directory:
        raise RuntimeError(f'${RECORDS_ENV} names no directory for the fault records')
    return Path(directory)


def record(name: str, **outcome) -> dict:
    """Write the measured outcome of one fault test to ``$FAULTS_OUT/name.json`` and return it."""
    directory = records_dir()
    directory.mkdir(parents=True, exist_ok=True)
    outcome = {'fault': name, **outcome}
    (directory / f'{name}.json').write_text(json.dumps(outcome, indent=2, default=float))
    return outcome


def _fmt(value, unit: str = '') -> str:
    if value is None:
        return '–'
    if isinstance(value, float):
        return f'{value:.3g}{unit}'
    return f'{value}{unit}'


def table(directory: Path) -> str:
    """The README table of every record in ``directory``."""
    rows = ['| # | fault | injected | times | crashes | non-finite outputs | messages lost | '
            'recovery (sim time) | notes |',
            '| ---: | --- | --- | ---: | ---: | ---: | ---: | ---: | --- |']
    records = [json.loads(path.read_text()) for path in directory.glob('*.json')]
    order = list(ITEMS)
    records.sort(key=lambda r: order.index(r['fault']) if r['fault'] in order else len(order))
    for r in records:
        rec = r.get('recovery_s')
        rows.append(f'| {ITEMS.get(r["fault"], "")} | {r["fault"]} | {r["injected"]} | '
                    f'{r["times"]} | {r.get("crashes", 0)} | '
                    f'{r.get("nonfinite_outputs", 0)} | {_fmt(r.get("messages_lost"))} | '
                    f'{_fmt(rec, " s")} | {r.get("notes", "")} |')
    return '\n'.join(rows)


if __name__ == '__main__':
    if len(sys.argv) < 2 and not os.environ.get(RECORDS_ENV):
        sys.exit(f'usage: python {sys.argv[0]} DIR   (or set ${RECORDS_ENV})')
    print(table(Path(sys.argv[1]) if len(sys.argv) > 1 else records_dir()))
