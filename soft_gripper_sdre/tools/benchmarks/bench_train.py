"""Training benchmark: ``tools.learning.train`` run again and again on each case, every stage's
time as the tool itself records it (``metrics.json``'s ``timings``), with its spread and the load.

    python -m soft_gripper_sdre.tools.benchmarks.bench_train [--runs 5]
        [--hand-data data/excitation] [--bags 'tendon3, 200 Hz=runs/t3_bags' ...]
        [--out runs/bench_train] [--write runs/bench_train.json]

A case is the hand's ``--data`` directory of .npz records (the default preset, the shipped
model's recipe) or a directory of bags with ``train/`` and ``val/`` inside (``train --bag``, the
gripper preset), named ``NAME=DIR``. Each run is a fresh process, the cases one after another,
each case's runs in a row, its stages read off the tool's ``stages [s]`` line (``metrics.json``
keeps them too). A row gives the total's median and min–max over the runs (the
stages the tool times, from reading the data to writing the report), each stage's median and its
share of the median total, the command's own wall time (Python's imports and start-up too), and
the 1-minute load average (median and min–max, read before each run): the machine is shared, and a
run beside other work is slower.
``--write`` keeps the rows as JSON, which ``tools.benchmarks.bench`` (``make bench``) puts in
BENCHMARKS.md (:func:`rows`).
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import re
import shutil
import statistics
import subprocess
import sys
import time

from soft_gripper_sdre.tools.learning import NOT_FIT

#: the stages the rows show, as metrics.json's ``timings`` names them
STAGES = ('read', 'labels', 'label_stage', 'simulation_stage', 'checkpoint', 'fitness',
          'finger_fits', 'loop_settings', 'report')
#: where ``make bench`` finds the rows
RESULTS = Path('runs/bench_train.json')


def _case(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition('=')
    if not sep or not name.strip() or not path.strip():
        raise argparse.ArgumentTypeError(f'--bags takes NAME=DIR, got {text!r}')
    return name.strip(), Path(path.strip())


def run_once(args: list[str], out: Path) -> dict:
    """One ``tools.learning.train`` run in its own process: its metrics' ``timings`` with the
    load average read before it (``load``) and the run's own wall time (``wall``)."""
    shutil.rmtree(out, ignore_errors=True)
    load = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.learning.train', *args,
                           '--out', str(out)], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode not in (0, NOT_FIT):         # NOT_FIT: trained, judged, timed
        raise RuntimeError(f'train {" ".join(args)} failed (exit {proc.returncode}): '
                           f'{proc.stderr[-1500:]}')
    metrics = json.loads((out / 'metrics.json').read_text())
    # the tool's line has every stage (the report's too, which metrics.json cannot hold)
    timings = {**metrics.get('timings', {}), **printed_stages(proc.stdout)}
    if 'total' not in timings:
        raise RuntimeError(f'train {" ".join(args)} printed no stages line')
    fitness = metrics.get('fitness') or {}
    derived = metrics.get('derived_settings') or {}
    return {'timings': timings, 'load': load, 'wall': wall,
            'fit': fitness.get('fit_for_control'),
            'free_run_mm': (1e3 * fitness['free_run']['rmse_m']
                            if 'free_run' in fitness else None),
            'bandwidth_hz': (derived.get('settings') or {}).get('bandwidth_hz'),
            'epochs_run': metrics.get('epochs_run')}


def printed_stages(stdout: str) -> dict[str, float]:
    """The stages [s] of the train tool's last ``stages [s], <total> in all: <stage> <s>, …``
    line, with ``total``; {} when it printed none."""
    for line in stdout.splitlines()[::-1]:
        head, sep, rest = line.partition(' in all: ')
        if line.startswith('stages [s], ') and sep:
            stages = dict(re.findall(r'([a-z_]+) ([0-9.]+)', rest))
            return {**{k: float(v) for k, v in stages.items()},
                    'total': float(head.split(', ')[1])}
    return {}


def summary(name: str, runs: list[dict]) -> dict:
    """A case's row: the runs' total (median, min, max) [s], each stage's median [s] and that
    median's share of the median total (medians of different runs: the shares need not add up
    to 1), the load (median, min, max), what the runs gave (verdicts, free-run errors, chosen
    bandwidths) and every run's timings."""
    totals = [r['timings']['total'] for r in runs]
    walls = [r['wall'] for r in runs]
    loads = [r['load'] for r in runs]
    median = statistics.median(totals)
    stages = {}
    for stage in STAGES:
        got = [r['timings'][stage] for r in runs if stage in r['timings']]
        if got:
            stages[stage] = {'median': statistics.median(got),
                             'share': statistics.median(got) / median}
    return {'case': name, 'runs': len(runs), 'total': [median, min(totals), max(totals)],
            'wall': [statistics.median(walls), min(walls), max(walls)],
            'load': [statistics.median(loads), min(loads), max(loads)], 'stages': stages,
            'fit': [r['fit'] for r in runs], 'free_run_mm': [r['free_run_mm'] for r in runs],
            'bandwidth_hz': [r['bandwidth_hz'] for r in runs],
            'timings': [r['timings'] for r in runs]}


def row_text(s: dict) -> tuple[str, str, str]:
    """(what, figure, note) of a case's summary, as BENCHMARKS.md's table takes them."""
    med, lo, hi = s['total']
    parts = [f'{k.replace("_", " ")} {v["median"]:.1f} s ({100 * v["share"]:.0f} %)'
             for k, v in s['stages'].items() if v['median'] >= 0.05]
    load = s['load']
    wall = (f'; the command from start to exit, Python\'s imports included: '
            f'{s["wall"][0]:.0f} s ({s["wall"][1]:.0f}–{s["wall"][2]:.0f})' if 'wall' in s else '')
    return (f'training, {s["case"]}', f'{med:.0f} s ({lo:.0f}–{hi:.0f})',
            f'median (min–max) of {s["runs"]} runs, load {load[0]:.1f} ({load[1]:.1f}–'
            f'{load[2]:.1f}); stages (median, share): ' + ', '.join(parts) + wall)


def rows(path: Path = RESULTS) -> list[tuple[str, str, str]]:
    """The rows kept by ``--write`` at ``path`` ([] when there are none)."""
    if not Path(path).is_file():
        return []
    return [row_text(s) for s in json.loads(Path(path).read_text())['cases']]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.bench_train',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--runs', type=int, default=5, help='runs per case (>= 1; default 5)')
    ap.add_argument('--hand-data', type=Path, default=None,
                    help="the hand's .npz records (tools.learning.collect's --out)")
    ap.add_argument('--bags', type=_case, action='append', default=[], metavar='NAME=DIR',
                    help='a bag case: DIR holds train/ and val/ (repeatable)')
    ap.add_argument('--out', type=Path, default=Path('runs/bench_train'),
                    help="the runs' output directory (each run replaces the last)")
    ap.add_argument('--write', type=Path, default=None, help='keep the rows here as JSON')
    a = ap.parse_args(argv)
    if a.runs < 1:
        ap.error(f'--runs must be >= 1, got {a.runs}')
    cases = []
    if a.hand_data is not None:
        if not a.hand_data.is_dir():
            ap.error(f'--hand-data {a.hand_data} is not a directory')
        cases.append(('the hand, .npz records, default preset', ['--data', str(a.hand_data)]))
    for name, path in a.bags:
        if not ((path / 'train').is_dir() and (path / 'val').is_dir()):
            ap.error(f'--bags {name}={path}: needs {path}/train and {path}/val')
        cases.append((f'{name}, bags, gripper preset',
                      ['--bag', str(path / 'train'), '--val-bag', str(path / 'val')]))
    if not cases:
        ap.error('give --hand-data and/or --bags NAME=DIR')
    results = []
    for name, args in cases:
        runs = []
        for k in range(a.runs):
            runs.append(run_once(args, a.out))
            t = runs[-1]['timings']
            print(f'{name}: run {k + 1}/{a.runs} {t["total"]:.1f} s (load {runs[-1]["load"]:.1f})',
                  flush=True)
        results.append(summary(name, runs))
        what, figure, note = row_text(results[-1])
        print(f'{what}: {figure}; {note}', flush=True)
        if a.write:
            a.write.parent.mkdir(parents=True, exist_ok=True)
            a.write.write_text(json.dumps({'cases': results, 'machine': {
                'cpus': os.cpu_count(), 'date': time.strftime('%Y-%m-%d')}}, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
