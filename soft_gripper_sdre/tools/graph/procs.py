"""Start and stop the node graph as separate processes (what ``ros2 run`` would start).

Used by the demo, the benchmarks, the multi-hand and multi-host runs and the multi-process tests.
Each node runs as the command of its :class:`~soft_gripper_sdre.nodes.graph.NodeSpec`,
``python -m soft_gripper_sdre.nodes.<name> --ros-args --params-file config/<name>.yaml -p ...``
(optionally behind a prefix such as ``ip netns exec <host>``), with its stdout/stderr in a log
file, DDS kept on loopback unless the caller's environment says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
import platform
import random
import signal
import subprocess
import sys
import time
from typing import Mapping

from soft_gripper_sdre.nodes.graph import RECORDED_BEFORE_START, NodeSpec, default_params_file

#: topics whose publishers a recorder must have matched before the simulator starts stepping
#: (the root graph's names)
WIRED_BEFORE_START = tuple(f'/{topic}' for topic in RECORDED_BEFORE_START)
#: the environment variables that decide whom a DDS participant discovers and how it talks to them
DDS_ENV = ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS',
           'FASTDDS_BUILTIN_TRANSPORTS')


#: the math libraries' kernels pinned to one code path that every x86-64 machine with AVX2 and
#: FMA runs, so numbers come out the same on each: OpenBLAS's Haswell kernels (numpy), MKL's AVX2
#: branch in strict conditional-numerical-reproducibility mode and ATen's AVX2 kernels (torch).
#: Without them an AVX-512 machine's OpenBLAS takes its SkylakeX kernels and parts from an AVX2
#: machine in the last bits (docs/model.md, "The same model on another machine")
PINNED_KERNELS = {'OPENBLAS_CORETYPE': 'Haswell', 'MKL_CBWR': 'AVX2,STRICT',
                  'ATEN_CPU_CAPABILITY': 'avx2'}


def cpu_runs_pinned_kernels() -> bool:
    """An x86-64 Linux machine with AVX2 and FMA: one that runs :data:`PINNED_KERNELS`."""
    if platform.machine() != 'x86_64':
        return False
    try:
        text = Path('/proc/cpuinfo').read_text()
    except OSError:
        return False
    flags = next((line.split(':', 1)[1].split() for line in text.splitlines()
                  if line.startswith('flags')), [])
    return {'avx2', 'fma'} <= set(flags)


def pinned_kernels(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The :data:`PINNED_KERNELS` that ``environ`` does not set already, where this machine runs
    them (else none)."""
    if not cpu_runs_pinned_kernels():
        return {}
    return {key: value for key, value in PINNED_KERNELS.items() if key not in environ}


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """The environment for the graph: DDS on loopback, a domain of its own and, where the CPU
    runs them, the :data:`PINNED_KERNELS` (a variable the caller set is kept)."""
    env = dict(os.environ)
    env.update(pinned_kernels(env))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    if domain_id is None:
        domain_id = int(env.get('ROS_DOMAIN_ID', '0')) or random.SystemRandom().randint(1, 101)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env.setdefault('PYTHONUNBUFFERED', '1')
    env.setdefault('OMP_NUM_THREADS', '1')
    return env


@dataclass
class NodeProcess:
    """One node process and its log file."""

    name: str
    popen: subprocess.Popen
    log_path: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors='replace')[-chars:]
        except OSError:
            return ''


@dataclass
class Graph:
    """A set of node processes started together and stopped in reverse order."""

    env: dict[str, str]
    log_dir: Path
    procs: dict[str, NodeProcess] = field(default_factory=dict)

    def start(self, node: str, params: dict | None = None,
              params_file: Path | None | str = 'default', name: str | None = None) -> NodeProcess:
        """Start the node ``node`` of the root namespace with its shipped parameters file (or
        ``params_file``) and the overrides ``params``; ``name`` keys the process and its log."""
        if params_file == 'default':
            params_file = default_params_file(node)
        return self.start_node(NodeSpec(node, node, params_file=params_file,
                                        parameters=dict(params or {})), key=name)

    def start_node(self, spec: NodeSpec, *, key: str | None = None, prefix: tuple[str, ...] = (),
                   env: dict[str, str] | None = None) -> NodeProcess:
        """Start the node ``spec`` describes as its own process.

        Args:
            spec: the node (its command line is :meth:`NodeSpec.command`).
            key: the process's name in :attr:`procs` and of its log file (default: the node name).
            prefix: run the command behind this, e.g. ``('ip', 'netns', 'exec', 'host_b')``.
            env: the process's environment (default: the graph's).
        """
        key = key or spec.name
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f'{key}.log'
        log = open(log_path, 'w', encoding='utf-8')  # noqa: SIM115 — closed by the child's exit
        popen = subprocess.Popen([*prefix, *spec.command(sys.executable)], env=env or self.env,
                                 stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        log.close()
        proc = NodeProcess(key, popen, log_path)
        self.procs[key] = proc
        return proc

    def stop(self, name: str, timeout: float = 10.0, sig: int = signal.SIGINT) -> int:
        """Signal one node and wait for it; escalate to SIGKILL after ``timeout``."""
        proc = self.procs[name]
        if proc.alive():
            proc.popen.send_signal(sig)
            try:
                proc.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.popen.kill()
                proc.popen.wait(5.0)
        return proc.popen.returncode

    def stop_all(self, timeout: float = 10.0) -> dict[str, int]:
        return {name: self.stop(name, timeout) for name in reversed(list(self.procs))}

    def wait(self, name: str, timeout: float, poll=None) -> int | None:
        """Wait for one node to exit by itself; ``poll()`` is called about 10× per second.
        Returns its exit code, or None on timeout or if another node died first."""
        deadline = time.monotonic() + timeout
        proc = self.procs[name]
        while time.monotonic() < deadline:
            if not proc.alive():
                return proc.popen.returncode
            dead = [p for p in self.procs.values() if p.name != name and not p.alive()]
            if dead:
                return None
            if poll is not None:
                poll()
            time.sleep(0.1)
        return None

    def __enter__(self) -> Graph:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


class DiagnosticsMonitor:
    """The newest /diagnostics values of every node of a graph, by node name, and every status
    received (``history``, in order).

    A node of its own rclpy Context in the calling process (the demo's progress bar and start-up
    wait, the graph benchmarks' figures); ``poll``/``spin_until`` take what has arrived.
    """

    def __init__(self, env: dict[str, str], name: str = 'diagnostics_monitor') -> None:
        os.environ.update({k: env[k] for k in DDS_ENV if k in env})
        from diagnostic_msgs.msg import DiagnosticArray
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from soft_gripper_sdre.nodes.topics import DIAGNOSTICS, STREAM_QOS

        self.values: dict[str, dict[str, str]] = {}         # by node name (the last one heard)
        self.by_full_name: dict[str, dict[str, str]] = {}   # by fully qualified name
        self.history: dict[str, list[dict[str, str]]] = {}  # by node name, every status heard
        self._ctx = Context()
        rclpy.init(context=self._ctx)
        self._node = Node(name, context=self._ctx)
        self._node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diag, STREAM_QOS)
        self._exec = SingleThreadedExecutor(context=self._ctx)
        self._exec.add_node(self._node)
        self._taken = 0                 # messages taken so far (poll: until none is left)

    def _on_diag(self, msg) -> None:
        self._taken += 1
        for status in msg.status:       # a status is named by its node's fully qualified name
            values = {kv.key: kv.value for kv in status.values}
            node = status.name.rsplit('/', 1)[-1]
            self.values[node] = values
            self.by_full_name[status.name] = values
            self.history.setdefault(node, []).append(values)

    def get(self, node: str, key: str, default: float = 0.0) -> float:
        """The newest value of ``key`` from ``node`` as a number (``default`` if none yet).
        ``node`` is a node name, or a fully qualified one (``/left_hand/simulator``) to tell the
        nodes of several namespaces apart."""
        table = self.by_full_name if node.startswith('/') else self.values
        try:
            return float(table.get(node, {}).get(key, default))
        except ValueError:
            return default

    def snapshot(self) -> dict[str, dict[str, str]]:
        """A copy of every node's newest values, by node name (a window's start or end for
        :func:`~soft_gripper_sdre.tools.graph.deploy.loop_report`)."""
        return {node: dict(values) for node, values in self.values.items()}

    def poll(self, most: int = 1000) -> None:
        """Take whatever has arrived (up to ``most`` messages), without waiting. One spin_once
        runs one ready entity, a message or one of the executor's own guard conditions, so spin
        until two in a row take nothing."""
        idle = 0
        for _ in range(most):
            before = self._taken
            self._exec.spin_once(timeout_sec=0.0)
            idle = idle + 1 if self._taken == before else 0
            if idle == 2:
                return

    def spin_until(self, predicate, timeout: float) -> bool:
        """Spin until ``predicate()`` holds or ``timeout`` seconds of wall time pass."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self._exec.spin_once(timeout_sec=0.05)
        return bool(predicate())

    def wait_steady(self, node: str, key: str, reports: int = 2, timeout: float = 15.0) -> bool:
        """Wait until ``reports`` reports of ``node`` arrived after this call and the last
        ``reports`` of them agree on ``key`` (e.g. a recorder that has taken every message a
        finished run published, however far a loaded machine left it behind); False after
        ``timeout`` seconds."""
        seen = len(self.history.get(node, []))

        def steady() -> bool:
            new = self.history.get(node, [])[seen:]
            return len(new) >= reports and len({v.get(key) for v in new[-reports:]}) == 1
        return self.spin_until(steady, timeout)

    def close(self) -> None:
        import rclpy
        self._exec.shutdown()
        self._node.destroy_node()
        rclpy.try_shutdown(context=self._ctx)
