"""An identification run's torque at each instant of run time (ROS-free; the excitation node holds
an :class:`ExcitationRun` and publishes, shows and logs what it returns).

Run time starts at the run's first tips. The run is, in order:

1. the first settle phase at zero torque (:class:`~soft_gripper_sdre.sim.settle.SettlePhase`):
   extended until enough tip messages were heard, every later run time shifted by the extension;
2. with a :class:`~soft_gripper_sdre.sim.excitation.LevelSearch`, its probes, each measured on
   the newest tips, until it has chosen the amplitude;
3. the :class:`~soft_gripper_sdre.sim.excitation.ExcitationPlan`, scaled to the chosen amplitude
   with its time 0 where the search ended (without a search: as given, from run time 0);

then the run is over. With the level per signal (``per_signal``, a factory of searches) phases 2
and 3 repeat for each signal of the plan: a search whose probes play that signal's start
(:meth:`~soft_gripper_sdre.sim.excitation.ExcitationPlan.own_probe`), its first probe at the
amplitude the previous signal was played at, then that signal alone at the amplitude it chose.

Every torque of the three phases is counted by the settle phase, which
knows the zero-torque answers before the first non-zero one (training's noise level); with
bounded inputs "zero" is the rest inputs (a vented chamber, slack tendons). The tips at
the run's start are kept: how far an excited tip moved from them is the run's excursion.
"""
from __future__ import annotations

import enum
from typing import Callable, NamedTuple

import numpy as np

from soft_gripper_sdre.sim.excitation import ExcitationPlan, LevelSearch
from soft_gripper_sdre.sim.settle import SettlePhase


class Phase(enum.Enum):
    """Where a run time falls."""

    SETTLE = 'the first settle phase, extended until enough tips were heard'
    PROBE = "the level search's probes and the settle phases between them"
    PLAY = "the plan's signals and the settle phases before them"
    OVER = 'past the end of the plan'


class RunStep(NamedTuple):
    """The run at one run time."""

    phase: Phase
    t: float | None          # search time (PROBE), plan time (PLAY, OVER); None while SETTLE
    u: np.ndarray | None     # the torque (n, 2) [N·m] or inputs (n, m); None when OVER
    first_torque: bool       # ``u`` is the first non-zero torque of the run
    level_chosen: bool       # the search chose the amplitude at this step (the plan is scaled)


#: a level search for a single-signal plan, its first probe at the given amplitude (None: the
#: search's own start)
SearchFactory = Callable[[ExcitationPlan, 'float | None'], LevelSearch]


class ExcitationRun:
    """Settle, probes, plan (module doc).

    Args:
        plan: the signals, settles, finger, limit and (without a search) amplitude.
        settle: the first settle phase.
        search: the amplitude search to run before the plan (None: the plan's amplitude).
        per_signal: level each signal on its own (module doc): the search of each signal's plan
            (``search`` is then not used).

    Attributes:
        plan: the plan being played (with ``per_signal``: the current signal's alone).
        whole: the plan of every signal as given.
        levels: (signal name, chosen amplitude) of each levelled plan so far.
    """

    def __init__(self, plan: ExcitationPlan, settle: SettlePhase,
                 search: LevelSearch | None = None,
                 per_signal: SearchFactory | None = None) -> None:
        self.whole = plan
        self.settle = settle
        self.per_signal = per_signal
        self.stages = ([plan.signal_plan(j) for j in range(len(plan.segments))]
                       if per_signal is not None else [plan])
        self.stage = 0
        self.plan = self.stages[0]
        self.search = search if per_signal is None else per_signal(self.plan, None)
        self.search_offset = 0.0                # run time at which search time 0 is [s]
        self.plan_offset = 0.0                  # run time at which plan time 0 is [s]
        self.rest: np.ndarray | None = None     # the tips at the start
        self.levels: list[tuple[str, float]] = []

    def start(self, tips: np.ndarray) -> None:
        """The run starts at ``tips`` (n, 3) [m]: the positions excursions are measured from."""
        self.rest = tips.copy()

    def excursion(self, tips: np.ndarray) -> float:
        """The largest distance of an excited tip from its starting position [m] (NaN counts as
        far)."""
        rows = slice(None) if self.plan.finger is None else [self.plan.finger]
        d = np.linalg.norm(tips[rows] - self.rest[rows], axis=-1)
        return float(np.inf if not np.all(np.isfinite(d)) else d.max())

    def at(self, t: float, tips: np.ndarray) -> RunStep:
        """The run at run time ``t`` [s] (``tips``: the newest, which the search measures)."""
        t = self.settle.run_time(t)
        if t is None:
            return self._answer(Phase.SETTLE, None, self.plan.rest_inputs())
        chosen = False
        while True:
            search = self.search
            if search is not None and not search.done:
                u = search.step(t - self.search_offset, tips)
                if not search.done:
                    return self._answer(Phase.PROBE, t - self.search_offset, u)
                self.plan = self.plan.scaled(search.amplitude)
                self.plan_offset = self.search_offset + search.end
                self.levels.append((self.plan.segments[0].signal.name if self.per_signal
                                    else 'all', search.amplitude))
                chosen = True
            tp = t - self.plan_offset
            if not self.plan.finished(tp):
                return self._answer(Phase.PLAY, tp, self.plan.torques(tp), chosen)
            if self.stage + 1 >= len(self.stages):
                return RunStep(Phase.OVER, tp, None, False, chosen)
            previous = self.search.amplitude
            self.stage += 1
            self.search_offset = self.plan_offset + self.plan.duration
            self.plan = self.stages[self.stage]
            self.search = self.per_signal(self.plan, previous)

    def _answer(self, phase: Phase, t: float | None, u: np.ndarray,
                chosen: bool = False) -> RunStep:
        return RunStep(phase, t, u, self.settle.answered(u - self.plan.rest), chosen)
