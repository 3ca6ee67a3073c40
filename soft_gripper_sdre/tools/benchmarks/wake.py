"""What waking up costs a loop node's Python: its message callback timed back to back, and after
the idle gap a lockstep period leaves each process (``make bench``'s wake-up rows).

    python -m soft_gripper_sdre.tools.benchmarks.wake [--quick]

The estimator's ``on_tips`` and the controller's ``on_estimate`` (the shipped defaults: the hand's
four fingers, ``sdre_ff``) are called in-process on CDR bytes, as the executor calls them, in four
ways taking turns: **warm** (back to back), after **sleeping** ``GAP_S`` (the CPU goes idle as it
does between a lockstep graph's messages), the same **holding the CPU wake-up latency** at 0 µs
(:class:`~soft_gripper_sdre.nodes.scheduling.CpuLatencyHold`; left out where not permitted) and
after **busy-waiting** ``GAP_S`` (the same gap, the CPU kept running). The floor of a lockstep
period (``bench.floor_rows``) counts the compute warm; these rows show what the same Python costs
run the way the graph runs it.
"""
from __future__ import annotations

import argparse
import time
from typing import Callable

import numpy as np

from soft_gripper_sdre.tools.benchmarks.spread import REPEATS, LoadWatch, figure

#: the idle gap before each call [s]: about what a 1 ms lockstep period leaves each loop process
GAP_S = 0.5e-3
#: how each call is prepared, in the order the rows give them
WAYS = ('warm', 'sleep', 'held', 'busy')
WORDS = {'warm': 'back to back', 'sleep': f'after sleeping {GAP_S * 1e3:g} ms',
         'held': f'after sleeping {GAP_S * 1e3:g} ms, the CPU wake-up latency held at 0 µs',
         'busy': f'after busy-waiting {GAP_S * 1e3:g} ms'}


def _busy_wait(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def _timed(call: Callable[[int], None], calls: int, before: Callable[[], None] | None,
           first: int) -> float:
    """The median wall time [s] of ``call(k)`` for k = first … first + calls − 1, each after
    ``before()`` (if any); the first tenth left out (caches and branch history settling)."""
    times = np.empty(calls)
    for i in range(calls):
        if before is not None:
            before()
        t0 = time.perf_counter()
        call(first + i)
        times[i] = time.perf_counter() - t0
    return float(np.median(times[calls // 10:]))


class _Callbacks:
    """The estimator and the controller on the shipped defaults in a context of their own, with
    the CDR bytes of their inputs: ``estimator(k)`` / ``controller(k)`` take the message of
    period k (stamps increase, so neither refuses one as old)."""

    def __init__(self, periods: int) -> None:
        import rclpy
        from rclpy.context import Context
        self.context = Context()
        rclpy.init(context=self.context)
        self.est = self.ctrl = None
        try:
            self._build(periods)
        except BaseException:
            self.close()
            raise

    def _build(self, periods: int) -> None:
        from soft_gripper_sdre.nodes.controller import ControllerNode
        from soft_gripper_sdre.nodes.estimator import EstimatorNode
        self.est = EstimatorNode(context=self.context)
        self.ctrl = ControllerNode(context=self.context)
        ns = int(round(self.est.p['control_period'] * 1e9))
        rest = np.asarray(self.ctrl.model.rest_tip[:2], dtype=float)
        tips = np.c_[np.repeat(rest[None], self.est.n, 0), np.zeros(self.est.n)]
        wiggle = 1e-4 * np.sin(np.arange(periods) / 50.0)        # a tip that moves a little
        self.tips = [self.est.cdr_tips.encode(k * ns, tips + w) for k, w in enumerate(wiggle)]
        x = np.c_[tips[:, :2], np.zeros((self.est.n, 2))]
        self.estimates = [self.ctrl.cdr_estimate.encode(k * ns, x + w) for k, w in
                          enumerate(wiggle)]
        offsets = np.arange(2) * ns
        pos = np.repeat(x[None, :, :2], 2, 0)
        zeros = np.zeros_like(pos)
        self.ctrl.on_reference(self.ctrl.cdr_plan.encode(0, offsets, pos, zeros, zeros))
        if self.ctrl.gate.plan is None:
            raise RuntimeError('the controller refused the benchmark\'s plan')

    def estimator(self, k: int) -> None:
        self.est.on_tips(self.tips[k])

    def controller(self, k: int) -> None:
        self.ctrl.on_estimate(self.estimates[k])

    def close(self) -> None:
        import rclpy
        for node in (self.est, self.ctrl):
            if node is not None:
                node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def wake_costs(repeats: int = REPEATS, calls: int = 2000) -> dict:
    """Per callback (``estimator``, ``controller``) and way of :data:`WAYS`, the median call [s]
    of each of ``repeats`` runs of ``calls`` calls, the ways taking turns run by run; ``held``
    only where the CPU wake-up latency can be held (else ``unheld`` says why). Also ``load``, a
    :class:`~soft_gripper_sdre.tools.benchmarks.spread.LoadWatch`.

    Raises:
        RuntimeError: a call was refused instead of answered (its time is not the answering path).
    """
    from soft_gripper_sdre.nodes.scheduling import CPU_LATENCY_ENV, CpuLatencyHold, hold_cpu_latency
    ways = list(WAYS)
    probe, said = hold_cpu_latency({CPU_LATENCY_ENV: '0'})
    if probe is None:
        ways.remove('held')
    else:
        probe.close()
    cb = _Callbacks(repeats * len(ways) * calls + 1)
    out: dict = {name: {w: [] for w in ways} for name in ('estimator', 'controller')}
    load = LoadWatch()
    load.note()
    k = 0                    # each callback's next period: its stamps run on without a jump
    try:
        for _ in range(repeats):
            for way in ways:
                hold = CpuLatencyHold(0) if way == 'held' else None
                before = {'warm': None, 'busy': lambda: _busy_wait(GAP_S)}.get(
                    way, lambda: time.sleep(GAP_S))
                try:
                    for name in out:
                        out[name][way].append(_timed(getattr(cb, name), calls, before, k))
                    k += calls
                finally:
                    if hold is not None:
                        hold.close()
        answered = (cb.est.diag.counters['estimates'], cb.ctrl.diag.counters['commands'])
    finally:
        cb.close()
    if answered != (k, k):                 # every call timed the whole path, none a refusal
        raise RuntimeError(f'{k} calls each, but {answered[0]} estimates and {answered[1]} '
                           'commands: the benchmark timed refusals')
    load.note()
    out['load'] = load
    if 'held' not in ways:
        out['unheld'] = f'the wake-up latency {said}'
    return out


def wake_rows(quick: bool = False) -> list[tuple[str, str, str]]:
    """One row per callback: warm, and each way after the gap with its ratio to warm."""
    repeats, calls = (2, 300) if quick else (REPEATS, 2000)
    costs = wake_costs(repeats, calls)
    load = costs.pop('load')
    unheld = costs.pop('unheld', None)
    rows = []
    what = {'estimator': "estimator's on_tips (decode, KF, encode, publish)",
            'controller': "controller's on_estimate (decode, sdre_ff, checks, encode, publish)"}
    for name, ways in costs.items():
        warm = float(np.median(ways['warm']))
        parts = [f'{WORDS[w]} {figure(ways[w])} ({np.median(ways[w]) / warm:.1f}×)'
                 for w in WAYS[1:] if w in ways]
        rows.append((f"a loop callback's Python, warm and after an idle gap: {what[name]}",
                     f'{figure(ways["warm"])} back to back',
                     '; '.join(parts + ([unheld] if unheld else []))
                     + f'; median (min–max) of {len(ways["warm"])} runs of {calls} calls, the '
                     f'ways taking turns; {load.text()}'))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.benchmarks.wake',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--quick', action='store_true', help='fewer, shorter runs (smoke test)')
    a = ap.parse_args(argv)
    for name, value, note in wake_rows(a.quick):
        print(f'| {name} | {value} | {note} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
