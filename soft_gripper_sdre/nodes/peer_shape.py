"""Whether the nodes that feed a controller filter and plan tips of its model's dimension.

A planar estimator (``task_dim`` 2) feeding a controller whose model is of 3-D tips hands it
estimates with z = 0 however the tip moves, and a planar trajectory node plans z = 0 for a tip
that rests elsewhere: nothing in those messages tells them from a 3-D tip at z = 0, so the
controller asks each publisher of its estimates and plans for its ``task_dim`` parameter instead
(``rcl_interfaces/GetParameters``, once per publisher, as publishers appear). A publisher of
another ``task_dim`` is a mismatch, named with the fix; a publisher without the parameter (a
lab's own estimator) or without parameter services is taken as it is. ``controller
--with-estimator`` checks its own estimator when it starts; this covers nodes started by hand.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import partial

from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node

#: the parameter each publisher is asked for
TASK_DIM = 'task_dim'


def _full_name(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


class PeerShapes:
    """Asks every publisher of ``topics`` (resolved names) for its ``task_dim`` and compares it
    with ``d``; :meth:`poll` at a slow rate (the node's /diagnostics), ``problem`` the first
    mismatch of a publisher still present (None: none), ``on_change(problem)`` called when it
    changes."""

    def __init__(self, node: Node, d: int, topics: Sequence[str], on_change=None) -> None:
        self._node, self._d, self._topics = node, d, tuple(topics)
        self._on_change = on_change
        self._clients: dict[str, object] = {}       # by the publisher node's full name
        self._asked: set[bytes] = set()             # publishers (gids) asked or answered
        self._wrong: dict[bytes, str] = {}          # publishers of another task_dim: why
        self.problem: str | None = None

    def poll(self) -> None:
        """Ask the publishers not yet asked whose parameter service is up; forget the
        mismatches of publishers gone."""
        present = set()
        for topic in self._topics:
            for info in self._node.get_publishers_info_by_topic(topic):
                gid = bytes(info.endpoint_gid)
                present.add(gid)
                if gid in self._asked:
                    continue
                peer = _full_name(info.node_namespace, info.node_name)
                client = self._clients.get(peer)
                if client is None:
                    client = self._node.create_client(GetParameters, f'{peer}/get_parameters')
                    self._clients[peer] = client
                if not client.service_is_ready():
                    continue                                    # asked at a later poll
                self._asked.add(gid)
                request = GetParameters.Request(names=[TASK_DIM])
                client.call_async(request).add_done_callback(
                    partial(self._answered, gid, peer, topic))
        self._asked &= present
        self._wrong = {gid: why for gid, why in self._wrong.items() if gid in present}
        self._update()

    def _answered(self, gid: bytes, peer: str, topic: str, future) -> None:
        response = future.result()
        values = [] if response is None else response.values
        if len(values) != 1 or values[0].type != ParameterType.PARAMETER_INTEGER:
            return                                  # no task_dim there: taken as it is
        theirs = values[0].integer_value
        if theirs != self._d:
            self._wrong[gid] = (f"{peer} publishes {topic} for task_dim {theirs}, but the model is "
                                f"of {self._d}-D tips: start it with -p task_dim:={self._d}")
            self._update()

    def _update(self) -> None:
        problem = next(iter(self._wrong.values()), None)
        if problem != self.problem:
            self.problem = problem
            if self._on_change is not None:
                self._on_change(problem)
