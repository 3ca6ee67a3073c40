"""Timestamps inside the loop's processes, to tell what makes a period late.

A process started with ``SGS_PROBE=<dir>`` and this package's probe directory first on its
``PYTHONPATH`` (:func:`probe_env`: a ``sitecustomize`` that calls :func:`install`) records, on
``time.perf_counter`` (CLOCK_MONOTONIC, one clock for every process of the machine):

* every **garbage collection**: its start and duration [s] and generation (``gc.callbacks``);
* every **subscription callback**: topic, entry and exit, and the message's leading stamp [ns] when
  it comes as raw CDR bytes (``Node.create_subscription`` wrapped);
* every **publish**: topic, start and end, the stamp of raw bytes (``Publisher.publish`` wrapped);
* every **timer callback**: entry and exit (``Node.create_timer`` wrapped: /diagnostics, watchdogs,
  a driver's or simulator's stepping timer);
* every **bag write** of the recorder: start and duration (``rosbags`` ``Writer.write`` wrapped).

The executor's wake-up is what lies between the driver's publish and the callback's entry (rclpy's
EventsExecutor is C++, its wait cannot be wrapped from Python).

Each record goes into a preallocated numpy array (no Python object per event, so the probe does
not feed the collector it watches); at exit the arrays are saved to
``<dir>/<program>-<pid>.npz``. :func:`late_causes` joins them with the driver's ticks
(:mod:`soft_gripper_sdre.tools.benchmarks.deploy_driver` saves its own when ``SGS_PROBE`` is set)
and attributes every late period.
"""
from __future__ import annotations

import atexit
import gc
import os
from pathlib import Path
import sys
import time

import numpy as np

#: events kept per kind (the oldest are kept; 60 s at 1 kHz with room)
CAPACITY = 200_000
#: the environment variable naming the directory the records go to
ENV = 'SGS_PROBE'
#: the topics a record names, by index (anything else: -1)
TOPICS = ('/tip_positions', '/state_estimate', '/torque_commands', '/grasp_reference',
          '/diagnostics', '/clock')


class Events:
    """A preallocated table of ``columns`` floats per event."""

    def __init__(self, columns: int) -> None:
        self.data = np.zeros((CAPACITY, columns))
        self.n = 0

    def add(self, *values: float) -> None:
        if self.n < CAPACITY:
            self.data[self.n] = values
            self.n += 1

    def rows(self) -> np.ndarray:
        return self.data[:self.n]


def _topic_index(name: str) -> int:
    return TOPICS.index(name) if name in TOPICS else -1


def _stamp(data) -> float:
    if isinstance(data, (bytes, bytearray)) and len(data) >= 12:
        sec, nsec = int.from_bytes(data[4:8], 'little', signed=True), \
            int.from_bytes(data[8:12], 'little')
        return float(sec * 1_000_000_000 + nsec)
    return -1.0


def install(out_dir: str | os.PathLike) -> None:
    """Start recording in this process (see the module doc); the records are saved at exit."""
    perf = time.perf_counter
    gcs, cbs, pubs, writes, timers = Events(3), Events(4), Events(4), Events(2), Events(2)
    started: list[float] = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        if phase == 'start':
            started[0] = perf()
        else:
            gcs.add(started[0], perf() - started[0], info.get('generation', -1))
    gc.callbacks.append(on_gc)

    from rclpy.node import Node
    from rclpy.publisher import Publisher

    create = Node.create_subscription

    def create_subscription(self, msg_type, topic, callback, *args, **kwargs):
        index = _topic_index(self.resolve_topic_name(topic))

        def timed(msg):
            t0 = perf()
            try:
                return callback(msg)
            finally:
                cbs.add(index, t0, perf(), _stamp(msg))
        return create(self, msg_type, topic, timed, *args, **kwargs)
    Node.create_subscription = create_subscription

    create_timer = Node.create_timer

    def create_timed_timer(self, period, callback, *args, **kwargs):
        def timed():
            t0 = perf()
            try:
                return callback()
            finally:
                timers.add(t0, perf())
        return create_timer(self, period, timed, *args, **kwargs)
    Node.create_timer = create_timed_timer

    publish = Publisher.publish

    def timed_publish(self, msg):
        t0 = perf()
        try:
            return publish(self, msg)
        finally:
            pubs.add(_topic_index(self.topic_name), t0, perf(), _stamp(msg))
    Publisher.publish = timed_publish

    try:
        from rosbags.rosbag2 import Writer
        write = Writer.write

        def timed_write(self, *args, **kwargs):
            t0 = perf()
            try:
                return write(self, *args, **kwargs)
            finally:
                writes.add(t0, perf() - t0)
        Writer.write = timed_write
    except ImportError:
        pass

    def save() -> None:
        tag = 'driver' if '--driver' in sys.argv else Path(sys.argv[0] or 'python').stem
        np.savez(Path(out_dir) / f'{tag}-{os.getpid()}.npz', gc=gcs.rows(), callbacks=cbs.rows(),
                 publishes=pubs.rows(), writes=writes.rows(), timers=timers.rows())
    atexit.register(save)


SITECUSTOMIZE = f'''import os
if os.environ.get({ENV!r}):
    from soft_gripper_sdre.tools.benchmarks.loop_probe import install
    install(os.environ[{ENV!r}])
'''


def probe_env(env: dict[str, str], out_dir: Path) -> dict[str, str]:
    """``env`` with the probe switched on: records to ``out_dir`` (made), a ``sitecustomize`` that
    installs the probe first on ``PYTHONPATH``."""
    boot = out_dir / 'boot'
    boot.mkdir(parents=True, exist_ok=True)
    (boot / 'sitecustomize.py').write_text(SITECUSTOMIZE)
    path = os.pathsep.join(p for p in (str(boot), env.get('PYTHONPATH', '')) if p)
    return {**env, ENV: str(out_dir), 'PYTHONPATH': path}


# -- reading the records ------------------------------------------------------------------------

def load(out_dir: Path) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """(the driver's ticks, {process tag: its records}) of one probed run in ``out_dir``."""
    ticks = dict(np.load(out_dir / 'ticks.npz'))
    procs = {}
    for path in sorted(out_dir.glob('*-*.npz')):
        procs[path.stem.rsplit('-', 1)[0]] = dict(np.load(path))
    return ticks, procs


def _overlap(starts: np.ndarray, durations: np.ndarray, lo: float, hi: float) -> float:
    """Seconds of the intervals (start, duration) inside [lo, hi]."""
    if not len(starts):
        return 0.0
    a = np.maximum(starts, lo)
    b = np.minimum(starts + durations, hi)
    return float(np.clip(b - a, 0.0, None).sum())


def _durations(seconds: np.ndarray) -> tuple[int, float, float, float]:
    """(count, median µs, p99.9 µs, max µs) of some events' durations."""
    us = 1e6 * seconds
    return (int(len(us)), round(float(np.median(us)), 1), round(float(np.percentile(us, 99.9)), 1),
            round(float(us.max()), 1))


def late_causes(out_dir: Path, gc_min: float = 50e-6) -> dict:
    """What made each late period of a probed deployment run late.

    A tick k is late when the command for tick k − 1 had not come back by it; that message's
    round trip [sent, received] (or [sent, tick k] if it never came) is split into **in** (tips
    sent → the loop process's tips callback entered: DDS and the executor's wake-up), **work**
    (callback entry → the command's publish returned: decode, KF, law, encode, write) and
    **back** (→ the driver's callback took it). Over the round trip: the collections of every loop
    process and the driver (ms, those longer than ``gc_min``), the loop processes' timer callbacks
    (ms), the recorder's bag writes (ms), and whether the tips callback waited for the one before
    it (the process busy: queued).

    Returns ``late`` (count), ``ticks``, the medians of in / work / back over all periods and over
    the late ones, and ``cause`` → count, each late period given to the first that holds: ``gc``
    (a collection over it), ``timer`` (a loop process's timer callbacks over the round trip
    > 0.2 ms), ``queued``, ``recorder`` (its writes over the round trip > 0.2 ms),
    ``in`` / ``work`` / ``back`` (the longest part: scheduling, the process not running)."""
    ticks, procs = load(out_dir)
    period = float(ticks['period'])
    period_ns = period * 1e9
    sent, received, late = ticks['sent'], ticks['received'], ticks['late']
    first = int(ticks['first'])
    loop = 'controller' if 'estimator' not in procs else 'estimator'
    cbs = procs[loop]['callbacks']
    tips_cb = cbs[cbs[:, 0] == TOPICS.index('/tip_positions')]
    cmd = np.concatenate([p['publishes'] for p in procs.values() if len(p['publishes'])])
    cmd = cmd[cmd[:, 0] == TOPICS.index('/torque_commands')]
    enter = {int(round(s / period_ns)): (t0, t1) for _, t0, t1, s in tips_cb}
    pub = {int(round(s / period_ns)): t1 for _, _, t1, s in cmd}
    t_lo, t_hi = sent[first], sent.max() + period
    inside = lambda ev: ev[(ev[:, 0] >= t_lo) & (ev[:, 0] <= t_hi)]  # noqa: E731
    gc_all = {tag: inside(p['gc']) for tag, p in procs.items()}
    gcs = {tag: g for tag, g in gc_all.items() if tag != 'recorder' and len(g)}
    writes = inside(procs.get('recorder', {}).get('writes', np.zeros((0, 2))))
    timers_all = {tag: inside(p.get('timers', np.zeros((0, 2)))) for tag, p in procs.items()}
    loop_timers = np.concatenate([timers_all[tag] for tag in ('estimator', 'controller')
                                  if tag in timers_all] or [np.zeros((0, 2))])
    parts: dict[str, list] = {'in': [], 'work': [], 'back': []}
    late_parts: dict[str, list] = {'in': [], 'work': [], 'back': []}
    causes: dict[str, int] = {}
    detail = []
    ks = np.arange(first + 1, len(sent))
    for k in ks:
        j = k - 1
        if sent[j] <= 0 or j not in enter or j not in pub:
            continue
        t_in, t_cb_end = enter[j]
        t_pub = pub[j]
        got = received[j] if received[j] > 0 else np.inf
        seg = {'in': t_in - sent[j], 'work': t_pub - t_in, 'back': got - t_pub}
        for name, v in seg.items():
            parts[name].append(v)
        if not (sent[k] > 0 and late[k]):
            continue
        for name, v in seg.items():
            late_parts[name].append(v)
        hi = min(got, sent[k]) if np.isfinite(got) else sent[k]
        gc_ms = {tag: 1e3 * _overlap(g[:, 0], np.where(g[:, 1] >= gc_min, g[:, 1], 0), sent[j],
                                     hi) for tag, g in gcs.items()}
        write_ms = 1e3 * _overlap(writes[:, 0], writes[:, 1], sent[j], hi)
        timer_ms = 1e3 * _overlap(loop_timers[:, 0], loop_timers[:, 1] - loop_timers[:, 0],
                                  sent[j], hi)
        before = tips_cb[(tips_cb[:, 3] < j * period_ns) & (tips_cb[:, 1] < t_in)
                         & (tips_cb[:, 2] > sent[j])]
        queued = len(before) > 0
        if any(v > 0 for v in gc_ms.values()):
            cause = 'gc'
        elif timer_ms > 0.2:
            cause = 'timer'
        elif queued:
            cause = 'queued'
        elif write_ms > 0.2:
            cause = 'recorder'
        else:
            cause = max(seg, key=lambda n: seg[n])
        causes[cause] = causes.get(cause, 0) + 1
        detail.append((int(k), cause, {n: round(1e6 * v) if np.isfinite(v) else None
                                       for n, v in seg.items()},
                       {t: round(v, 2) for t, v in gc_ms.items() if v}, round(write_ms, 2),
                       round(timer_ms, 2)))
    med = lambda xs: round(1e6 * float(np.median(xs))) if xs else None  # noqa: E731
    p99 = lambda xs: round(1e6 * float(np.percentile(xs, 99))) if xs else None  # noqa: E731
    finite = lambda xs: [x for x in xs if np.isfinite(x)]  # noqa: E731
    summary = {
        'ticks': int((sent[first:] > 0).sum()), 'late': int(late[first:][sent[first:] > 0].sum()),
        'median_us': {n: med(v) for n, v in parts.items()},
        'p99_us': {n: p99(finite(v)) for n, v in parts.items()},
        'late_median_us': {n: med(finite(v)) for n, v in late_parts.items()},
        'cause': causes,
        'gc': {tag: (int(len(g)), round(1e3 * float(g[:, 1].sum()), 2),
                     round(1e3 * float(g[:, 1].max()), 2) if len(g) else 0.0)
               for tag, g in gc_all.items()},
        'timers': {tag: _durations(t[:, 1] - t[:, 0]) for tag, t in timers_all.items() if len(t)},
        'writes': ((int(len(writes)), round(1e6 * float(np.median(writes[:, 1])), 1),
                    round(1e6 * float(np.percentile(writes[:, 1], 99.9)), 1),
                    round(1e6 * float(writes[:, 1].max()), 1)) if len(writes) else None),
        'detail': detail[:40],
    }
    return summary


def graph_periods(out_dir: Path, period: float = 1e-3) -> dict:
    """Where a period of the simulated graph goes, from a probed
    :func:`~soft_gripper_sdre.tools.benchmarks.graph_run.run_graph` (estimator and controller as
    separate processes): per period k (its tips' stamp), medians and p99 [µs] of

    ``hop tips`` (the simulator's publish of the tips began → the estimator's callback entered),
    ``estimator`` (→ its publish of the estimate returned), ``hop estimate`` (→ the controller's
    callback entered), ``controller`` (→ its publish of the command returned), ``hop command``
    (→ the simulator's command callback entered) and ``simulator`` (→ its publish of the next tips
    began: physics and everything else it does in a period); with ``period`` (tips to tips), the
    round trips (tips out → command in) longer than ``period`` [s] and the medians of their
    parts, and per process its collections in the stepping (count, total ms, longest ms)."""
    procs = {}
    for path in sorted(out_dir.glob('*-*.npz')):
        procs[path.stem.rsplit('-', 1)[0]] = dict(np.load(path))
    tips, est, cmd = (TOPICS.index(t) for t in ('/tip_positions', '/state_estimate',
                                                '/torque_commands'))

    def by_stamp(rows: np.ndarray, topic: int, column: int) -> dict[int, float]:
        rows = rows[rows[:, 0] == topic]
        return {int(s): t for s, t in zip(rows[:, 3], rows[:, column])}
    sim, e, c = procs['simulator'], procs['estimator'], procs['controller']
    marks = [by_stamp(sim['publishes'], tips, 1), by_stamp(e['callbacks'], tips, 1),
             by_stamp(e['publishes'], est, 2), by_stamp(c['callbacks'], est, 1),
             by_stamp(c['publishes'], cmd, 2), by_stamp(sim['callbacks'], cmd, 1)]
    names = ('hop tips', 'estimator', 'hop estimate', 'controller', 'hop command', 'simulator')
    stamps = sorted(set.intersection(*(set(m) for m in marks)))
    seg: dict[str, list[float]] = {n: [] for n in (*names, 'period')}
    for a, b in zip(stamps[:-1], stamps[1:]):
        t = [m[a] for m in marks] + [marks[0][b]]
        for name, t0, t1 in zip(names, t[:-1], t[1:]):
            seg[name].append(t1 - t0)
        seg['period'].append(t[-1] - t[0])
    skip = len(stamps) // 10                      # the first tenth: start-up, cold caches
    out = {n: (round(1e6 * float(np.median(v[skip:]))), round(1e6 * float(np.percentile(
        v[skip:], 99)))) for n, v in seg.items() if len(v) > skip}
    trip = np.sum([seg[n][skip:] for n in names[:5]], axis=0) if len(stamps) > skip + 1 else []
    slow = np.asarray(trip) > period
    out['round trips longer than a period'] = int(slow.sum())
    if slow.any():
        out['their parts'] = {n: round(1e6 * float(np.median(np.asarray(seg[n][skip:])[slow])))
                              for n in names[:5]}
    lo = marks[0][stamps[skip]] if stamps else 0.0
    hi = marks[0][stamps[-1]] if stamps else 0.0
    out['gc'] = {}
    for tag, p in procs.items():
        g = p['gc'][(p['gc'][:, 0] >= lo) & (p['gc'][:, 0] <= hi)]
        out['gc'][tag] = (int(len(g)), round(1e3 * float(g[:, 1].sum()), 2),
                          round(1e3 * float(g[:, 1].max()), 2) if len(g) else 0.0)
    out['periods'] = max(len(stamps) - 1 - skip, 0)
    return out
