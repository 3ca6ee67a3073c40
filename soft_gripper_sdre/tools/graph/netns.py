"""Two hosts on one Linux machine: two network namespaces joined by a veth pair, the DDS settings
that make their processes talk over that link, and a fault that takes the link down.

The pair's addresses (:data:`SIM_ADDRESS`, :data:`CTL_ADDRESS`, /24) exist only inside the
namespaces, each with its loopback up and a route for multicast (224.0.0.0/4) over its end of
the link, as a host on a LAN has through its default route (without one the split graph did not
connect on its first start: docs/deployment.md). A process runs on a host behind
``ip netns exec <host>`` (so it needs root and iproute2). DDS between the hosts
(:meth:`HostPair.env`, see docs/deployment.md):

* ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``: UDP only. Two network namespaces share one kernel and one
  /dev/shm, so Fast DDS's shared-memory transport would otherwise carry the data past the link;
* ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``: discovery on the hosts' own subnet (each namespace has
  nothing else). ``LOCALHOST`` would not do: Jazzy's rmw_fastrtps then replaces the built-in
  transports with its own shared memory + UDP pair, and FASTDDS_BUILTIN_TRANSPORTS is ignored;
* ``ROS_STATIC_PEERS=<the other host>``: the other host's address for unicast discovery
  announcements as well.
"""
from __future__ import annotations

from dataclasses import dataclass
import json
import os
import secrets
import shutil
import subprocess
import threading
import time

SIM_ADDRESS = '10.231.0.1'
CTL_ADDRESS = '10.231.0.2'
PREFIX_LENGTH = 24
#: multicast leaves each host over its end of the link (the split graph connects with it)
MULTICAST_ROUTE = '224.0.0.0/4'


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be made here (not root, no iproute2), or None."""
    if shutil.which('ip') is None:
        return 'iproute2 (the ip command) is not installed'
    if os.geteuid() != 0:
        return 'network namespaces need root (ip netns add)'
    probe = f'sgs_probe_{secrets.token_hex(3)}'
    made = subprocess.run(['ip', 'netns', 'add', probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f'ip netns add failed: {made.stderr.strip()}'
    subprocess.run(['ip', 'netns', 'delete', probe], capture_output=True)
    return None


def _ip(*args: str, netns: str | None = None) -> str:
    cmd = ['ip'] + (['-n', netns] if netns else []) + list(args)
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'{" ".join(cmd)}: {done.stderr.strip()}')
    return done.stdout


@dataclass(frozen=True)
class HostPair:
    """Two network namespaces joined by a veth pair: the simulator's host and the controller's.

    Names carry a random tag so runs side by side do not meet; :meth:`create` builds them,
    :meth:`remove` (also on leaving a ``with`` block) deletes both namespaces, and the veth pair
    with them."""

    tag: str

    @classmethod
    def new(cls) -> HostPair:
        return cls(secrets.token_hex(4))

    @property
    def sim_ns(self) -> str:
        return f'sgs_{self.tag}_sim'

    @property
    def ctl_ns(self) -> str:
        return f'sgs_{self.tag}_ctl'

    @property
    def sim_link(self) -> str:          # interface names: at most 15 characters
        return f'sgs{self.tag}s'

    @property
    def ctl_link(self) -> str:
        return f'sgs{self.tag}c'

    def create(self) -> HostPair:
        try:
            _ip('netns', 'add', self.sim_ns)
            _ip('netns', 'add', self.ctl_ns)
            _ip('link', 'add', self.sim_link, 'netns', self.sim_ns, 'type', 'veth',
                'peer', 'name', self.ctl_link, 'netns', self.ctl_ns)
            for ns, link, address in ((self.sim_ns, self.sim_link, SIM_ADDRESS),
                                      (self.ctl_ns, self.ctl_link, CTL_ADDRESS)):
                _ip('addr', 'add', f'{address}/{PREFIX_LENGTH}', 'dev', link, netns=ns)
                _ip('link', 'set', 'lo', 'up', netns=ns)
                _ip('link', 'set', link, 'up', netns=ns)
                _ip('route', 'add', MULTICAST_ROUTE, 'dev', link, netns=ns)
        except RuntimeError:
            self.remove()
            raise
        return self

    def remove(self) -> None:
        """Delete both namespaces (and so the veth pair); quiet if they are gone already."""
        for ns in (self.sim_ns, self.ctl_ns):
            subprocess.run(['ip', 'netns', 'delete', ns], capture_output=True)

    def __enter__(self) -> HostPair:
        return self.create()

    def __exit__(self, *exc) -> None:
        self.remove()

    def exists(self) -> bool:
        names = _ip('netns', 'list')
        return any(line.split()[0] in (self.sim_ns, self.ctl_ns)
                   for line in names.splitlines() if line.strip())

    def interfaces(self, ns: str) -> list[str]:
        """The interface names in the namespace ``ns``."""
        return [link['ifname'] for link in json.loads(_ip('-j', 'link', 'show', netns=ns))]

    def traffic(self) -> dict[str, int]:
        """Bytes and packets the simulator's end of the link has sent and received."""
        stats = json.loads(_ip('-j', '-s', 'link', 'show', 'dev', self.sim_link,
                               netns=self.sim_ns))[0]['stats64']
        return {'tx_bytes': stats['tx']['bytes'], 'rx_bytes': stats['rx']['bytes'],
                'tx_packets': stats['tx']['packets'], 'rx_packets': stats['rx']['packets']}

    def exec_prefix(self, ns: str) -> tuple[str, ...]:
        return ('ip', 'netns', 'exec', ns)

    def env(self, ns: str, base: dict[str, str]) -> dict[str, str]:
        """``base`` with DDS over UDP only, discovering the other host (see module doc)."""
        peer = CTL_ADDRESS if ns == self.sim_ns else SIM_ADDRESS
        return {**base, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'ROS_STATIC_PEERS': peer,
                'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}


@dataclass
class LinkFault:
    """Take ``link`` down once the simulator's sim time reaches ``at`` s, and up ``seconds`` later
    (wall time). An ``on_poll`` of :func:`~soft_gripper_sdre.tools.graph.hands.run_graphs`."""

    link: str
    at: float
    seconds: float
    down_sim_time: float | None = None
    down_wall: float | None = None
    up_wall: float | None = None

    def __call__(self, monitor, graphs) -> None:
        if self.down_wall is not None or monitor.get('simulator', 'sim_time') < self.at:
            return
        _ip('link', 'set', 'dev', self.link, 'down')
        self.down_wall, self.down_sim_time = time.monotonic(), monitor.get('simulator', 'sim_time')
        threading.Timer(self.seconds, self._up).start()

    def _up(self) -> None:
        _ip('link', 'set', 'dev', self.link, 'up')
        self.up_wall = time.monotonic()
