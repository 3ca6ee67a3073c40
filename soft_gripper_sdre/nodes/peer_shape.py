"""Whether the nodes that feed a controller filter and plan tips of its model's dimension.

A planar estimator (``task_dim`` 2) feeding a controller whose model is of 3-D tips hands it
estimates with z = 0 however the tip moves, and a planar trajectory node plans z = 0 for a tip
that rests elsewhere: nothing in those messages tells them from a 3-D tip at z = 0, so the
controller asks each publisher of its estimates and plans for its ``task_dim`` parameter instead
(``rcl_interfaces/GetParameters``, once per publisher, as publishers appear: a timer looks every
:data:`POLL_PERIOD`, and a request unanswered after :data:`ANSWER_TIMEOUT` is sent again). A
publisher of another ``task_dim`` is a mismatch, named with the fix; a publisher without the
parameter (a lab's own estimator) is taken as it is. ``controller --with-estimator`` checks its
own estimator when it starts; this covers nodes started by hand.
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import partial
import time

from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node

#: the parameter each publisher is asked for
TASK_DIM = 'task_dim'
#: how often the publishers are looked at [s]
POLL_PERIOD = 0.25
#: a request unanswered this long is dropped and sent again [s]
ANSWER_TIMEOUT = 3.0


def _full_name(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


class PeerShapes:
    """Asks every publisher of ``topics`` (resolved names) for its ``task_dim`` and compares it
    with ``d``; ``problem`` is the first mismatch of a publisher still present (None: none),
    ``wrong_topics`` the topics such publishers publish on, ``on_change(problem)`` is called when
    the problem changes."""

    def __init__(self, node: Node, d: int, topics: Sequence[str], on_change=None) -> None:
        self._node, self._d, self._topics = node, d, tuple(topics)
        self._on_change = on_change
        self._clients: dict[str, object] = {}       # by the publisher node's full name
        self._answered: set[bytes] = set()          # publishers (gids) whose answer came
        self._waiting: dict[bytes, tuple] = {}      # gid → (client, future, when sent)
        self._wrong: dict[bytes, tuple[str, str]] = {}  # another task_dim's: (why, topic)
        self.problem: str | None = None
        #: the topics a publisher of another task_dim publishes on
        self.wrong_topics: frozenset[str] = frozenset()
        self._timer = node.create_timer(POLL_PERIOD, self.poll) if self._topics else None

    def poll(self) -> None:
        """Ask the publishers not yet answered whose parameter service is up (again when a
        request went unanswered); forget what publishers gone said."""
        present, now = set(), time.monotonic()
        for topic in self._topics:
            for info in self._node.get_publishers_info_by_topic(topic):
                gid = bytes(info.endpoint_gid)
                present.add(gid)
                if gid in self._answered:
                    continue
                if gid in self._waiting:
                    client, future, sent = self._waiting[gid]
                    if now - sent < ANSWER_TIMEOUT:
                        continue
                    client.remove_pending_request(future)
                    del self._waiting[gid]
                peer = _full_name(info.node_namespace, info.node_name)
                client = self._clients.get(peer)
                if client is None:
                    client = self._node.create_client(GetParameters, f'{peer}/get_parameters')
                    self._clients[peer] = client
                if not client.service_is_ready():
                    continue                                    # asked at a later poll
                future = client.call_async(GetParameters.Request(names=[TASK_DIM]))
                self._waiting[gid] = (client, future, now)
                future.add_done_callback(partial(self._on_answer, gid, peer, topic))
        self._answered &= present
        self._waiting = {g: w for g, w in self._waiting.items() if g in present}
        self._wrong = {g: why for g, why in self._wrong.items() if g in present}
        self._update()

    def _on_answer(self, gid: bytes, peer: str, topic: str, future) -> None:
        waiting = self._waiting.get(gid)
        if waiting is None or waiting[1] is not future:
            return                                  # gone, or asked again since
        del self._waiting[gid]
        self._answered.add(gid)
        response = future.result()
        values = [] if response is None else response.values
        if len(values) != 1 or values[0].type != ParameterType.PARAMETER_INTEGER:
            return                                  # no task_dim there: taken as it is
        theirs = values[0].integer_value
        if theirs != self._d:
            self._wrong[gid] = (f"{peer} publishes {topic} for task_dim {theirs}, but the model is "
                                f"of {self._d}-D tips: start it with -p task_dim:={self._d}", topic)
            self._update()

    def _update(self) -> None:
        problem = next((why for why, _ in self._wrong.values()), None)
        self.wrong_topics = frozenset(topic for _, topic in self._wrong.values())
        if problem != self.problem:
            self.problem = problem
            if self._on_change is not None:
                self._on_change(problem)
