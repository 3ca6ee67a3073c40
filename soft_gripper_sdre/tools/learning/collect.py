"""Run excitation signals on one finger and write the dataset (one ``.npz`` per signal).

    python -m soft_gripper_sdre.tools.learning.collect --signals u1 u2 u3 u4 --out data/excitation

Each record starts from a freshly built finger settled 0.5 s at u = 0, then applies u[k] over
[t_k, t_k + Δt) for 10 s at Δt = 1 ms. The finger is mounted like a hand finger (rolled 15°), so
the learned model applies to each finger of the hand. File contents (SI, finger base frame):

    t (N,) s · u (N,2) N·m · tip (N,3) m measured (noisy if --noise-std > 0), untranslated ·
    rest_tip (3,) · tip_true, vel_true (N,3) at t_k · acc_true (N,3) mean acceleration over
    [t_k, t_k+Δt), i.e. the response to u[k] · q, qd (N,10) · dt · signal · noise_std · seed ·
    format_version · sim_config (JSON)
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import os
from pathlib import Path
import sys

import numpy as np
from tqdm import tqdm

from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.sim.signals import (
    DURATION,
    IDENTIFYING_SIGNALS,
    PAPER_SIGNALS,
    SIGNALS,
    get_signal,
)

FORMAT_VERSION = 1
DEFAULT_SIGNALS = PAPER_SIGNALS + IDENTIFYING_SIGNALS


def collect_signal(name: str, config: SimConfig | None = None, duration: float = DURATION,
                   progress: bool = False) -> dict[str, np.ndarray]:
    """Apply signal ``name`` to a fresh finger and return the dataset record (see module doc)."""
    config = config or SimConfig(scene='finger')
    if config.scene != 'finger':
        raise ValueError(f"excitation data is collected on the 'finger' scene, "
                         f"got {config.scene!r}")
    dt = config.control_period
    n = int(round(duration / dt))
    t = np.arange(n) * dt
    u = get_signal(name)(t)
    rec = {key: np.empty((n, width)) for key, width in
           (('tip', 3), ('tip_true', 3), ('vel_true', 3), ('acc_true', 3), ('q', 10), ('qd', 10))}
    with GripperSim(config) as sim:
        steps = tqdm(range(n), desc=f'collect {name}', unit='step', mininterval=0.5,
                     disable=not progress, leave=False)
        for k in steps:
            truth = sim.truth()
            rec['tip'][k] = sim.measure()[0]
            rec['tip_true'][k] = truth.tip_pos[0]
            rec['vel_true'][k] = truth.tip_vel[0]
            rec['q'][k] = truth.q[0]
            rec['qd'][k] = truth.qd[0]
            sim.step(u[k:k + 1])
            rec['acc_true'][k] = sim.truth().tip_acc[0]     # (v_{k+1} − v_k) / Δt: caused by u[k]
        rest = sim.rest_tip[0].copy()
    return dict(t=t, u=u, rest_tip=rest, dt=np.float64(dt), signal=np.str_(name),
                noise_std=np.float64(config.noise_std), seed=np.int64(config.seed),
                format_version=np.int64(FORMAT_VERSION), sim_config=np.str_(config.to_json()),
                **rec)


def write_record(path: Path, record: dict[str, np.ndarray]) -> Path:
    """Write one record as an uncompressed ``.npz`` (no pickled objects: load with
    allow_pickle=False)."""
    np.savez(path, **record)
    return path


def _usage_error(parser: argparse.ArgumentParser, message: str):
    parser.print_usage(sys.stderr)
    print(f'{parser.prog}: error: {message}', file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.learning.collect',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--signals', nargs='+', default=list(DEFAULT_SIGNALS),
                        help=f'signals to run (known: {", ".join(SIGNALS)}; default: %(default)s)')
    parser.add_argument('--out', required=True, type=Path, help='output directory')
    parser.add_argument('--duration', type=float, default=DURATION, help='seconds per signal')
    parser.add_argument('--noise-std', type=float, default=0.0, help='tip measurement noise σ [m]')
    parser.add_argument('--seed', type=int, default=0, help='seed of the measurement noise')
    parser.add_argument('--mount-roll-deg', type=float, default=15.0,
                        help='finger base roll (15 = as mounted in the hand, 0 = upright)')
    args = parser.parse_args(argv)

    unknown = [s for s in args.signals if s not in SIGNALS]
    if unknown:
        _usage_error(parser, f'unknown signal(s) {", ".join(unknown)}; known: {", ".join(SIGNALS)}')
    if not (np.isfinite(args.duration) and args.duration > 0):
        _usage_error(parser, f'--duration must be > 0 s, got {args.duration}')
    try:
        config = SimConfig(scene='finger', noise_std=args.noise_std, seed=args.seed,
                           mount_roll_deg=args.mount_roll_deg)
    except ValueError as exc:
        _usage_error(parser, str(exc))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _usage_error(parser, f'cannot create output directory {args.out}: {exc.strerror}')
    if not os.access(args.out, os.W_OK):
        _usage_error(parser, f'output directory {args.out} is not writable')

    for i, name in enumerate(tqdm(args.signals, desc='signals', unit='signal')):
        # a different noise stream per signal, reproducible from --seed
        record = collect_signal(name, replace(config, seed=args.seed + i), args.duration,
                                progress=True)
        path = write_record(args.out / f'{name}.npz', record)
        tqdm.write(f'{path}: {record["t"].size} samples, tip range '
                   f'{1e3 * np.ptp(record["tip_true"], axis=0).round(2)} mm')
    return 0


if __name__ == '__main__':
    sys.exit(main())
