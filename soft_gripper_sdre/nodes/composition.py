"""The estimator in another node's process: ``controller --with-estimator``.

The estimator hands each estimate to its host in-process (no DDS hop, no second process to wake
per period) and still publishes it on ``state_estimate`` for everyone else. Both stay nodes of
their own, with their names, parameters and /diagnostics; one executor spins them
(docs/performance.md "The deployment loop"). The host is built first and told nothing of the
estimator beyond the callable that takes an estimate.
"""
from __future__ import annotations

from typing import Callable, Sequence, TypeVar

import numpy as np
from rclpy.node import Node

from soft_gripper_sdre.nodes.cli import format_help
from soft_gripper_sdre.nodes.estimator import PARAMS as ESTIMATOR_PARAMS
from soft_gripper_sdre.nodes.estimator import EstimatorNode
from soft_gripper_sdre.nodes.graph import HOSTS, wiring_key
from soft_gripper_sdre.nodes.params import Param

#: the command-line flag that runs the estimator node in the controller's process
WITH_ESTIMATOR = HOSTS['estimator'][1]

HostNode = TypeVar('HostNode', bound=Node)


def with_estimator(make_host: Callable[[], HostNode],
                   taker: Callable[[HostNode], Callable[[int, np.ndarray], None]],
                   **estimator_kwargs) -> tuple[Node, HostNode]:
    """(the estimator, the host) as two nodes of one process: ``make_host()`` builds the host
    (without a ``state_estimate`` subscription of its own), ``taker(host)`` is what gets each
    estimate (stamp [ns], the (n, 4) state); ``estimator_kwargs`` go to the estimator's
    constructor (``context=``). Both count the link in their /diagnostics wiring (a
    reader of the estimator's estimates, a writer of the host's), so the graph's start rule sees
    the loop wired as with two processes."""
    host = make_host()
    try:
        estimator = EstimatorNode(**estimator_kwargs)
    except BaseException:
        host.destroy_node()
        raise
    estimator.listeners.append(taker(host))
    topic = estimator.pub.topic_name
    estimator.in_process_wiring = {wiring_key('readers', topic): 1}
    host.in_process_wiring = {wiring_key('writers', topic): 1}
    return estimator, host


def composed_help(executable: str, summary: str, host_params: Sequence[Param]) -> str:
    """``<host> --with-estimator --help``: the host's parameters, then the estimator's, every
    one with its own meaning; a name both declare is said to reach both nodes."""
    own = {p.name for p in host_params}
    shared = [p.name for p in ESTIMATOR_PARAMS if p.name in own]
    heading = ("parameters of the estimator node in this process (-p NAME:=VALUE reaches both "
               "nodes, each taking the names it declares: "
               + (f"{', '.join(shared)} set both, each with its own meaning above and below; "
                  if shared else '')
               + "a parameters file's /**/estimator section sets the estimator's alone):")
    return format_help(executable, summary, host_params, f'{WITH_ESTIMATOR} ',
                       [(heading, ESTIMATOR_PARAMS)])


def composed_params(host_params: Sequence[Param]) -> tuple[Param, ...]:
    """The parameters a composed command line may set: the host's and the estimator's (a ``-p``
    reaches both nodes; each takes the names it declares)."""
    own = {p.name for p in host_params}
    return (*host_params, *(p for p in ESTIMATOR_PARAMS if p.name not in own))
