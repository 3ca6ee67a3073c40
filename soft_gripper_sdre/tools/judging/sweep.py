"""Tracking vs position weight under measurement noise, and why high gains fail.

    python -m soft_gripper_sdre.tools.judging.sweep --out runs/sweep

For each position weight q_pos and noise σ it runs the grasp in-process (sim → KF → SDRE, the
node graph's loop without the topics; R and q_vel at their defaults) and scores the free-space
RMSE of the *true* tip, as % of each finger's excursion (the worst finger is reported). Beside it,
the spectral radius of the same 1 ms loop closed around the full linearised 10-joint finger with
friction off. Each point is run without and with the torque roll-off
(:func:`soft_gripper_sdre.analysis.ground_truth.loop_spectral_radius`). Writes ``sweep.json``,
``sweep.png`` and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.judging.sweep',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=Path('runs/sweep'))
    ap.add_argument('--q-pos', type=float, nargs='+', default=[2.5e5, 5e5, 1e6, 2e6, 4e6])
    ap.add_argument('--noise', type=float, nargs='+', default=[0.0, 5e-5, 2e-4], help='σ [m]')
    ap.add_argument('--lowpass', type=float, nargs='+', default=None,
                    help='torque roll-off frequencies to compare [Hz] '
                         '(0 = off; default: 0 and the default)')
    ap.add_argument('--duration', type=float, default=6.0, help='sim time per run [s]')
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    a = ap.parse_args(argv)
    if any(q <= 0 for q in a.q_pos) or any(s < 0 for s in a.noise) or a.duration <= 0:
        ap.error('q_pos and duration must be > 0, noise >= 0')
    from tqdm import tqdm

    from soft_gripper_sdre.analysis.closed_loop import EstimatorSettings, run_closed_loop
    from soft_gripper_sdre.analysis.ground_truth import linear_finger, loop_spectral_radius
    from soft_gripper_sdre.analysis.plots import plot_sweep
    from soft_gripper_sdre.control.laws import make_law
    from soft_gripper_sdre.control.tracking import DEFAULT_LOWPASS_HZ, DEFAULT_WEIGHTS, Weights
    from soft_gripper_sdre.control.trajectory import GraspProfile
    from soft_gripper_sdre.learning.model import SDCModel, set_torch_threads
    from soft_gripper_sdre.sim.hand import SimConfig

    set_torch_threads(1)
    a.out.mkdir(parents=True, exist_ok=True)
    model = SDCModel()
    est = EstimatorSettings()
    plant = linear_finger(1e-3)
    rows = []
    lowpass = a.lowpass if a.lowpass is not None else [0.0, DEFAULT_LOWPASS_HZ]
    combos = [(q, s, f) for f in lowpass for s in a.noise for q in a.q_pos]
    for q, sigma, fc in tqdm(combos, desc='sweep', unit='run'):
        w = Weights(q, DEFAULT_WEIGHTS['q_vel'], DEFAULT_WEIGHTS['r'])
        r = run_closed_loop(make_law('sdre', model, w, 0.0625, lowpass_hz=fc), duration=a.duration,
                            sim_config=SimConfig(scene='hand', noise_std=sigma),
                            profile=GraspProfile(others='open'), estimator=est)
        pct = [m.rmse_pct for m in r.metrics]
        rho, freq = loop_spectral_radius(plant, model, w.Q, w.R, est.accel_psd, est.meas_std,
                                         lowpass_hz=fc)
        rows.append({'q_pos': q, 'noise_m': sigma, 'lowpass_hz': fc,
                     'worst_rmse_pct': float(np.nanmax(pct)), 'rmse_pct': [float(p) for p in pct],
                     'saturated_fraction': float(r.saturated.any(axis=2).mean()),
                     'fallback_fraction': float(r.fallback.mean()),
                     'frictionless_radius': rho, 'frictionless_mode_hz': freq})
    (a.out / 'sweep.json').write_text(json.dumps(rows, indent=2) + '\n')
    plot_sweep(rows, a.out / 'sweep.png')
    print('| roll-off | q_pos | σ [mm] | worst-finger RMSE [% of excursion] | saturated steps | '
          'frictionless loop radius |')
    print('| ---: | ---: | ---: | ---: | ---: | ---: |')
    for row in rows:
        off = 'off' if row['lowpass_hz'] == 0 else f'{row["lowpass_hz"]:g} Hz'
        print(f'| {off} | {row["q_pos"]:.2g} | {1e3 * row["noise_m"]:.2f} | '
              f'{row["worst_rmse_pct"]:.2f} | {100 * row["saturated_fraction"]:.1f} % | '
              f'{row["frictionless_radius"]:.4f} ({row["frictionless_mode_hz"]:.0f} Hz) |')
    print(f'wrote {a.out / "sweep.json"} and {a.out / "sweep.png"}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
