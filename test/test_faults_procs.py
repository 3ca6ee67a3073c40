"""Fault injection on the multi-process graph: crashed nodes, and recording under load and signals.

Every node is its own process (what ``ros2 run`` starts, ``tools/procs.py``); a probe node in the
test process listens to the loop. A victim is killed with SIGKILL mid-grasp and started again;
the lockstep simulator holds per its ``on_timeout`` meanwhile, the graph resumes, no torque is
non-finite, and tracking comes back on target. Slow: each run is tens of seconds of wall time.
"""
from __future__ import annotations

import signal
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
import numpy as np
import pytest
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from faults_common import on_target, record, recovery_time, tracking_error
from rosutil import Probe, ros_context, spin_until
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.topics import (CUBE_CONTACTS, DIAGNOSTICS, GRASP_REFERENCE, LOOP_QOS,
                                            REFERENCE_QOS, STATE_ESTIMATE, STREAM_QOS, TIP_POSITIONS,
                                            TORQUE_COMMANDS)
from soft_gripper_sdre.tools.procs import Graph, ros_env
from soft_gripper_sdre.trajectory import GraspProfile

pytestmark = [pytest.mark.ros, pytest.mark.slow]

MS = 1_000_000
#: the grasp of test_faults.py: close over 0.1 … 0.9 s, hold, open over 1.1 … 1.9 s
SHORT = dict(t_start=0.1, t_close=0.8, t_hold=0.2, t_open=0.8, others='hold')
#: what each victim publishes, so the test sees when it is back
OUTPUT = {'controller': TORQUE_COMMANDS, 'estimator': STATE_ESTIMATE, 'trajectory': GRASP_REFERENCE}
KILL_AT = 0.3           # sim time of the crash: the grasping fingers are closing in free space
AFTER = 1.0             # sim time the run goes on after the victim is back


def _stamp(msg) -> int:
    return cv.from_time(msg.header.stamp)


def _last_diagnostics(msgs, node: str) -> dict[str, str]:
    last = {}
    for msg in msgs:
        for status in msg.status:
            if status.name.endswith(node):
                last = {kv.key: kv.value for kv in status.values}
    return last


@pytest.mark.parametrize('victim', ['controller', 'estimator', 'trajectory'])
def test_crashed_node_is_restarted_and_the_grasp_recovers(victim, tmp_path):
    env = ros_env()
    params = {'estimator': {}, 'trajectory': dict(SHORT), 'controller': {},
              'simulator': {'min_tip_subscribers': 3, 'lockstep_timeout': 0.05, 'on_timeout': 'hold'}}
    with ros_context() as (ctx, executor), Graph(env, tmp_path / 'logs') as graph:
        probe = Probe(ctx)
        subs = {t: probe.listen(msg, t, qos) for t, msg, qos in (
            (TIP_POSITIONS, PoseArray, LOOP_QOS), (TORQUE_COMMANDS, JointState, LOOP_QOS),
            (STATE_ESTIMATE, MultiDOFJointTrajectory, LOOP_QOS), (CUBE_CONTACTS, JointState, STREAM_QOS),
            (GRASP_REFERENCE, MultiDOFJointTrajectory, REFERENCE_QOS),
            (DIAGNOSTICS, DiagnosticArray, STREAM_QOS))}
        executor.add_node(probe)
        got = probe.received
        for node in ('estimator', 'trajectory', 'controller'):
            graph.start(node, params[node])
        assert spin_until(executor, lambda: all(subs[t].get_publisher_count() > 0 for t in OUTPUT.values()),
                          60.0), f'graph not up: {[p.log_tail(300) for p in graph.procs.values()]}'
        graph.start('simulator', params['simulator'])

        def sim_ns() -> int:
            return _stamp(got[TIP_POSITIONS][-1]) if got[TIP_POSITIONS] else -1

        def all_alive() -> bool:
            return all(p.alive() for p in graph.procs.values())

        assert spin_until(executor, lambda: sim_ns() >= KILL_AT * cv.NS or not all_alive(), 120.0)
        assert all_alive(), {n: p.log_tail(500) for n, p in graph.procs.items() if not p.alive()}
        proc = graph.procs[victim].popen
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        killed_ns, killed_wall = sim_ns(), time.monotonic()
        n_out, n_cmd = len(got[OUTPUT[victim]]), len(got[TORQUE_COMMANDS])
        restart = dict(params[victim])
        if victim == 'trajectory':          # the restarted node must not take the bent tips as rest
            rest = cv.msg_to_tips(got[TIP_POSITIONS][0], 4)[1][:, :2]
            restart['rest_pose'] = ', '.join(f'{v!r}' for v in rest.ravel().tolist())
        graph.start(victim, restart, name=victim)
        # back: the restarted victim publishes for an instant after the crash
        assert spin_until(executor, lambda: any(_stamp(m) > killed_ns for m in got[OUTPUT[victim]][n_out:]),
                          120.0), graph.procs[victim].log_tail()
        # the loop is back once a torque command computed from an estimate (not the controller's
        # zero safe command) answers an instant after the crash
        def tracking_again() -> int | None:
            return next((_stamp(m) for m in got[TORQUE_COMMANDS][n_cmd:] if _stamp(m) >= victim_ns
                         and np.any(cv.msg_to_torques(m, 4)[1] != 0.0)), None)
        victim_ns = next(_stamp(m) for m in got[OUTPUT[victim]][n_out:] if _stamp(m) > killed_ns)
        assert spin_until(executor, lambda: tracking_again() is not None, 120.0), graph.procs['controller'].log_tail()
        back_ns = tracking_again()
        back_wall = time.monotonic() - killed_wall
        assert spin_until(executor, lambda: sim_ns() >= back_ns + AFTER * cv.NS or not all_alive(), 300.0)
        alive = {n: p.alive() for n, p in graph.procs.items()}
        codes = graph.stop_all()
        spin_until(executor, lambda: False, 1.0)            # final diagnostics
        diag = {n: _last_diagnostics(got[DIAGNOSTICS], n) for n in ('simulator', 'controller')}

    assert all(alive.values()), alive
    assert all(code == 0 for code in codes.values()), codes
    t, tips = zip(*(cv.msg_to_tips(m, 4) for m in got[TIP_POSITIONS]))
    t = np.asarray(t)
    tips = np.asarray(tips)[..., :2]
    assert np.all(np.diff(t) == MS)              # every period on the probe, none lost
    torques = [cv.msg_to_torques(m, 4)[1] for m in got[TORQUE_COMMANDS]]
    assert all(np.all(np.isfinite(u)) for u in torques)
    steps = int(diag['simulator']['steps'])
    lost = steps + 1 - len(t)
    timeouts = int(diag['simulator'].get('timeouts', 0))
    safe = int(diag['controller'].get('safe_commands', 0))
    if victim == 'estimator':
        assert safe > 0                          # the controller commanded zero meanwhile
    else:
        assert timeouts > 0                      # the simulator held the last command meanwhile
    forces = np.asarray([m.effort for m in got[CUBE_CONTACTS]])
    k = np.minimum(t // (10 * MS), len(forces) - 1)
    err, free, excursion = tracking_error(t / cv.NS, tips, forces[k] > 0, GraspProfile(**SHORT), tips[0])
    ends, ok = on_target(t / cv.NS, err, free, excursion)
    assert ok[ends < KILL_AT].all()                # on target before the crash
    rec = recovery_time(t / cv.NS, err, free, excursion, since=back_ns / cv.NS)
    outage = (back_ns - killed_ns) / cv.NS
    print(f'{victim}: killed at {killed_ns / cv.NS:.3f} s, back at {back_ns / cv.NS:.3f} s '
          f'({back_wall:.1f} s wall), recovery {rec:.3f} s; timeouts {timeouts}, safe {safe}, lost {lost}')
    assert rec <= 1.0, rec
    assert lost == 0
    hold = (f'simulator held the last command for {timeouts} periods' if victim != 'estimator'
            else f'controller sent zero torque for {safe} periods')
    record(f'crashed_{victim}', injected=f'SIGKILL of the {victim} process at t = {killed_ns / cv.NS:.3f} s, '
           'then restarted', times=1, crashes=0, nonfinite_outputs=0, messages_lost=lost,
           recovery_s=rec, notes=f'{hold}; back {outage:.3f} s of sim time ({back_wall:.1f} s wall) '
           'after the kill')


def _spawn_recorder(env, bag, name: str, log_dir):
    """A second recorder process under its own node name (procs.Graph names nodes by module)."""
    import subprocess
    import sys
    log = open(log_dir / f'{name}.log', 'w', encoding='utf-8')  # noqa: SIM115 — closed below
    proc = subprocess.Popen([sys.executable, '-m', 'soft_gripper_sdre.nodes.recorder', '--ros-args',
                             '-r', f'__node:={name}', '-p', f'output:={bag}'], env=env, stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    log.close()
    return proc


def test_recording_a_10s_grasp_loses_nothing_and_signals_leave_readable_bags(tmp_path):
    """Three recorders on the 5-process graph over a 10 s grasp at 1 ms: one to the end (every
    message the nodes counted as published is in its bag), one stopped by SIGINT and one by SIGTERM
    mid-run (each bag opens and holds every loop message up to the signal, without a gap)."""
    from soft_gripper_sdre.bag import read_bag, topic_counts
    duration = 10.0
    env = ros_env()
    logs = tmp_path / 'logs'
    logs.mkdir()
    bags = {'full': tmp_path / 'full', 'SIGINT': tmp_path / 'sigint', 'SIGTERM': tmp_path / 'sigterm'}
    with ros_context() as (ctx, executor), Graph(env, logs) as graph:
        probe = Probe(ctx)
        tips_sub = probe.listen(PoseArray, TIP_POSITIONS, LOOP_QOS)
        probe.listen(DiagnosticArray, DIAGNOSTICS, STREAM_QOS)
        executor.add_node(probe)
        graph.start('recorder', {'output': str(bags['full'])})
        extra = {sig: _spawn_recorder(env, bags[sig], f'recorder_{sig.lower()}', logs)
                 for sig in ('SIGINT', 'SIGTERM')}
        for node in ('estimator', 'trajectory', 'controller'):
            graph.start(node)

        def recorders_wired() -> bool:      # every recorder hears the loop's publishers
            seen = {}
            for msg in probe.received[DIAGNOSTICS][-50:]:
                for s in msg.status:
                    if 'recorder' in s.name:
                        seen[s.name] = {kv.key: kv.value for kv in s.values}
            return len(seen) == 3 and all(int(v.get(f'publishers /{t}', 0)) > 0 for v in seen.values()
                                          for t in (STATE_ESTIMATE, TORQUE_COMMANDS, GRASP_REFERENCE))
        assert spin_until(executor, recorders_wired, 90.0), [p.log_tail(300) for p in graph.procs.values()]
        graph.start('simulator', {'duration': duration, 'min_tip_subscribers': 6})
        signalled = {}
        for sig, at in (('SIGINT', 3.0), ('SIGTERM', 6.0)):
            assert spin_until(executor, lambda: probe.received[TIP_POSITIONS]
                              and _stamp(probe.received[TIP_POSITIONS][-1]) >= at * cv.NS, 600.0)
            extra[sig].send_signal(getattr(signal, sig))
            signalled[sig] = _stamp(probe.received[TIP_POSITIONS][-1])
        for proc in extra.values():
            assert proc.wait(30) == 0
        assert graph.wait('simulator', 900.0, lambda: executor.spin_once(timeout_sec=0.0)) == 0
        codes = graph.stop_all()
    assert all(code == 0 for code in codes.values()), codes
    assert tips_sub is not None

    full = read_bag(bags['full'])
    counts = topic_counts(bags['full'])
    last = {}
    for _, msg in full['/diagnostics']:
        for s in msg.status:
            last[s.name.lstrip('/')] = {kv.key: kv.value for kv in s.values}
    steps = int(last['simulator']['steps'])
    assert steps == int(round(duration / 1e-3))
    published = {'/clock': steps + 1, '/tip_positions': steps + 1,
                 '/joint_states': steps // 10 + 1, '/cube_pose': steps // 10 + 1, '/cube_contacts': steps // 10 + 1,
                 '/state_estimate': int(last['estimator']['estimates']),
                 '/torque_commands': int(last['controller']['commands'])
                 + int(last['controller'].get('safe_commands', 0)),
                 '/grasp_reference': int(last['trajectory']['references'])}
    lost = {t: n - counts.get(t, 0) for t, n in published.items()}
    print(f'published {published}; bag {counts}; signals at {signalled}')
    assert all(v == 0 for v in lost.values()), lost
    for sig, at in signalled.items():
        part = read_bag(bags[sig])                          # opens: metadata.yaml was written
        for topic in ('/tip_positions', '/state_estimate', '/torque_commands'):
            stamps = [_stamp(m) for _, m in part[topic]]
            assert stamps == [_stamp(m) for _, m in full[topic][:len(stamps)]], (sig, topic)
        tips = [_stamp(m) for _, m in part['/tip_positions']]
        assert tips == list(range(0, tips[-1] + 1, MS)) and tips[-1] >= at - 20 * MS, (sig, tips[-1], at)
    record('recording', injected=f'3 recorders on a {duration:g} s grasp at 1 ms (5-process graph); '
           'SIGINT to one at ~3 s, SIGTERM to one at ~6 s', times=1, crashes=0, nonfinite_outputs=0,
           messages_lost=sum(lost.values()), recovery_s=None,
           notes=f'{sum(published.values())} messages published = in the full bag; the signalled bags '
                 f'open and hold every loop message up to t = {signalled["SIGINT"] / cv.NS:.3f} s and '
                 f'{signalled["SIGTERM"] / cv.NS:.3f} s')
