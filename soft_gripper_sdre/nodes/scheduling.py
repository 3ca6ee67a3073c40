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

A process at real-time priority can also ask the kernel to keep every CPU's wake-up latency low
(:class:`CpuLatencyHold`, the PM QoS request cyclictest makes): an idle CPU then polls instead of
halting, and a message that wakes a process of the loop is taken up at once. Each hop of the loop
costs tens of microseconds less, but on the virtual machine we measure on the longest stalls did
not get shorter and the 500 Hz loop was late more often (docs/performance.md, "Waking up"), so it
is asked for, not implied: ``SOFT_GRIPPER_CPU_LATENCY_US=0`` (or any number of microseconds) in
the environment of a process at real-time priority. Writing the request needs root or write access
to ``/dev/cpu_dma_latency`` (a udev rule); without it the process runs on, says so in its log and
in /diagnostics (``cpu_latency``).
"""
from __future__ import annotations

import os
import shutil
import struct

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


#: the kernel's PM QoS request for CPU wake-up latency: while a process keeps this device open with
#: a latency written to it, no CPU of the machine enters an idle state slower than that to leave
CPU_LATENCY_DEVICE = '/dev/cpu_dma_latency'
#: environment variable: the wake-up latency [µs] a process at real-time priority asks for (unset
#: or off: none)
CPU_LATENCY_ENV = 'SOFT_GRIPPER_CPU_LATENCY_US'
LATENCY_HOW = (f'run as root, or give the user write access to {CPU_LATENCY_DEVICE} (a udev rule: '
               'KERNEL=="cpu_dma_latency", GROUP="<group>", MODE="0660")')


class CpuLatencyHold:
    """The machine's CPU wake-up latency held at ``us`` µs until :meth:`close` (or the process
    ends: the kernel drops the request with the file).

    Raises:
        OSError: the device cannot be opened for writing (not Linux, or not permitted).
    """

    def __init__(self, us: int = 0, device: str = CPU_LATENCY_DEVICE) -> None:
        self.us = us
        self._fd: int | None = os.open(device, os.O_WRONLY)
        try:
            os.write(self._fd, struct.pack('i', us))
        except OSError:
            self.close()
            raise

    @property
    def held(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> 'CpuLatencyHold':
        return self

    def __exit__(self, *_exc) -> None:
        self.close()


def cpu_latency_request(environ=os.environ) -> int | None:
    """The wake-up latency [µs] a process at real-time priority asks for: ``environ``'s
    :data:`CPU_LATENCY_ENV`; None when it is unset, empty or ``off``.

    Raises:
        ValueError: the variable is neither ``off`` nor an integer from 0 to 2000000000 µs.
    """
    text = environ.get(CPU_LATENCY_ENV, '').strip()
    if not text or text.lower() == 'off':
        return None
    try:
        us = int(text)
    except ValueError:
        us = -1
    if not 0 <= us <= 2_000_000_000:
        raise ValueError(f'{CPU_LATENCY_ENV}={text!r}: expected off or an integer number of '
                         'microseconds from 0 to 2000000000')
    return us


def hold_cpu_latency(environ=os.environ,
                     device: str = CPU_LATENCY_DEVICE) -> tuple[CpuLatencyHold | None, str]:
    """What a process at real-time priority holds: (the hold, or None; the ``cpu_latency`` it
    reports). Not permitted or not available is said, never raised.

    Raises:
        ValueError: a bad :data:`CPU_LATENCY_ENV` (:func:`cpu_latency_request`).
    """
    us = cpu_latency_request(environ)
    if us is None:
        return None, f'not asked for ({CPU_LATENCY_ENV} unset or off)'
    try:
        return CpuLatencyHold(us, device), f'{us} µs, held by this process'
    except PermissionError:
        return None, f'not held: {device} is not writable for this user; {LATENCY_HOW}'
    except OSError as exc:
        return None, f'not held: {device}: {exc.strerror}'


_PROCESS_HOLD: list[tuple[CpuLatencyHold | None, str]] = []     # this process's, once asked


def process_cpu_latency(environ=os.environ) -> str | None:
    """This process's ``cpu_latency`` report: at real-time priority the hold made for it (once,
    kept until the process ends, :func:`hold_cpu_latency`); None at ordinary priority.

    Raises:
        ValueError: a bad :data:`CPU_LATENCY_ENV`.
    """
    if not realtime():
        return None
    if not _PROCESS_HOLD:
        _PROCESS_HOLD.append(hold_cpu_latency(environ))
    return _PROCESS_HOLD[0][1]
