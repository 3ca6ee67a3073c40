"""Real-time priority for the loop's processes: what a process runs under, whether this user may
give one SCHED_FIFO, and the command prefix that does.

On a machine shared with other work the loop's periods are late when a process of the loop waits
for a core (docs/performance.md, "Real-time priority"). Under SCHED_FIFO a process that becomes
runnable takes a core from every ordinary (SCHED_OTHER) process at once; Linux keeps 5 % of each
second for the ordinary ones (``/proc/sys/kernel/sched_rt_runtime_us``), and the loop needs a
fraction of a core. A process started behind ``chrt -f <priority>`` runs there with every thread
it starts (the DDS threads included: a thread inherits its creator's policy), which is what the
tools' ``--realtime`` and the launch file's ``realtime_priority`` do, and what a lab types in front
of ``ros2 run`` (:func:`soft_gripper_sdre.nodes.graph.realtime_prefix`).

Setting SCHED_FIFO needs root, CAP_SYS_NICE, or an ``rtprio`` limit for the user
(``/etc/security/limits.conf``: ``<user> - rtprio 98``, then a new login).
"""
from __future__ import annotations

import os
import shutil

#: the priorities a loop process may be given (99 is left to the kernel's own threads)
FIFO_RANGE = (1, 98)

_POLICIES = {os.SCHED_OTHER: 'SCHED_OTHER', os.SCHED_FIFO: 'SCHED_FIFO', os.SCHED_RR: 'SCHED_RR',
             os.SCHED_BATCH: 'SCHED_BATCH', os.SCHED_IDLE: 'SCHED_IDLE'}
HOW = ('run as root, or give the user CAP_SYS_NICE or an rtprio limit '
       '(/etc/security/limits.conf: <user> - rtprio 98, then log in again)')


def describe(pid: int = 0) -> str:
    """The scheduling of ``pid``'s main thread (0: the calling thread): ``'SCHED_FIFO 50'``, or
    ``'SCHED_OTHER nice 0'`` for the ordinary policies."""
    policy = os.sched_getscheduler(pid)
    name = _POLICIES.get(policy, f'policy {policy}')
    if policy in (os.SCHED_FIFO, os.SCHED_RR):
        return f'{name} {os.sched_getparam(pid).sched_priority}'
    return f'{name} nice {os.getpriority(os.PRIO_PROCESS, pid)}'


def realtime(pid: int = 0) -> bool:
    return os.sched_getscheduler(pid) in (os.SCHED_FIFO, os.SCHED_RR)


def fifo_problem(priority) -> str | None:
    """Why a process of this user cannot be started under SCHED_FIFO at ``priority``, or None.

    Tried on the calling thread and put back at once, so the answer is the kernel's own."""
    if isinstance(priority, bool) or not isinstance(priority, int) \
            or not FIFO_RANGE[0] <= priority <= FIFO_RANGE[1]:
        return (f'real-time priority must be an integer from {FIFO_RANGE[0]} to {FIFO_RANGE[1]}, '
                f'got {priority!r}')
    if shutil.which('chrt') is None:
        return 'real-time priority needs chrt (util-linux) on the PATH; it is not there'
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return f'SCHED_FIFO priority {priority} is not permitted for this user: {HOW}'
    except OSError as exc:
        return f'SCHED_FIFO priority {priority} was refused: {exc.strerror}'
    os.sched_setscheduler(0, policy, param)
    return None


