"""A CPU hog for the realtime graph benchmark, and the figures of the run around it.

:class:`CpuHog` starts one busy process per core once the simulator's sim time reaches a given
instant (polled with the benchmark's
:class:`~soft_gripper_sdre.tools.graph.procs.DiagnosticsMonitor`); :func:`phase_figures` splits the
simulator's successive /diagnostics into the windows before, during and after it, and sums each
phase's lateness and loop latency. Used by
:func:`soft_gripper_sdre.tools.benchmarks.bench_graph.hog_run` and its test.
"""
from __future__ import annotations

import os
import subprocess
import sys

#: the phases of a run with a CPU hog
PHASES = ('before', 'during', 'after')
#: the "after" windows start this long after the hog was seen to end [s of sim time]; the monitor
#: sees sim time in the 1 Hz /diagnostics, so up to a second late
SETTLE_S = 2.0


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


class CpuHog:
    """Busy processes, one per core, started by :meth:`poll` once sim time reaches ``at``."""

    def __init__(self, at: float, seconds: float) -> None:
        self.at, self.seconds = at, seconds
        self.procs: list[subprocess.Popen] = []
        self.span: tuple[float, float] | None = None  # sim time the monitor saw at its start, end
        self._start = 0.0

    def poll(self, monitor) -> None:
        """Start the hog once the monitor's simulator sim time reaches ``at``; note when it
        ended."""
        sim_time = monitor.get('simulator', 'sim_time')
        if not self.procs and sim_time >= self.at:
            busy = (f'import time\nend = time.monotonic() + {self.seconds}\n'
                    'while time.monotonic() < end: pass')
            self.procs = [subprocess.Popen([sys.executable, '-c', busy])
                          for _ in range(os.cpu_count() or 1)]
            self._start = sim_time
        elif self.procs and self.span is None and all(p.poll() is not None for p in self.procs):
            self.span = (self._start, sim_time)

    def stop(self) -> None:
        """End the busy processes (if still running) and reap them."""
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait()


def phase_figures(history: list[dict[str, str]], hog_start: float,
                  hog_end: float) -> dict[str, dict[str, float]]:
    """Lateness and latency of the phases of a run with a hog from ``hog_start`` to ``hog_end``
    [s of sim time], from the simulator's successive /diagnostics ``history``.

    Returns, for each of :data:`PHASES` (the windows between two /diagnostics that end before the
    hog but start :data:`SETTLE_S` after t = 0, past the start-up; that overlap it; and that start
    :data:`SETTLE_S` after it), the window count ``windows``, the share
    of late and of safe periods (``late``, ``safe``), and the loop latency [µs]: the median of the
    windows' p50 (``p50``), the largest p99 and max (``p99``, ``max``).
    """
    nan = float('nan')
    rows = [{k: _number(v) for k, v in values.items() if _number(v) is not None}
            for values in history if 'sim_time' in values]
    phases: dict[str, list[tuple[dict, dict]]] = {p: [] for p in PHASES}
    for prev, cur in zip(rows, rows[1:]):
        begin, end = prev.get('sim_time', 0.0), cur.get('sim_time', 0.0)
        if end <= begin:
            continue
        phase = ('before' if SETTLE_S <= begin and end <= hog_start
                 else 'after' if begin >= hog_end + SETTLE_S
                 else 'during' if begin < hog_end and end > hog_start else None)
        if phase:
            phases[phase].append((prev, cur))
    out = {}
    for phase, windows in phases.items():
        def total(key: str) -> float:
            return sum(cur.get(key, 0.0) - prev.get(key, 0.0) for prev, cur in windows)
        steps = total('steps')
        p50 = sorted(cur['recent_latency_us_p50'] for _, cur in windows
                     if 'recent_latency_us_p50' in cur)
        out[phase] = {'windows': len(windows),
                      'late': total('late_periods') / steps if steps else nan,
                      'safe': total('safe_periods') / steps if steps else nan,
                      'p50': p50[len(p50) // 2] if p50 else nan,
                      'p99': max((cur.get('recent_latency_us_p99', nan) for _, cur in windows),
                                 default=nan),
                      'max': max((cur.get('recent_latency_us_max', nan) for _, cur in windows),
                                 default=nan)}
    return out
