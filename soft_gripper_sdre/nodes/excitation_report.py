"""What the excitation node shows of its run: the /diagnostics values and the log lines at the
start (with where its limit came from), at each step (the signal or probe being played, the plan
time), when the level search has chosen the amplitude, and at the first non-zero torque (how
many zero-torque answers training will find before it)."""
from __future__ import annotations

from soft_gripper_sdre.nodes.common import Diagnostics
from soft_gripper_sdre.nodes.topics import TORQUE_COMMANDS
from soft_gripper_sdre.sim.excitation_run import ExcitationRun, Phase, RunStep
from soft_gripper_sdre.sim.settle import MIN_SETTLE_SAMPLES

#: what the node is doing in each phase of the run, for /diagnostics
ACTIVITY = {Phase.SETTLE: 'settling until settle_samples tips were heard',
            Phase.PROBE: 'probing the level', Phase.PLAY: 'playing'}


class RunReport:
    """The run's values in ``diag`` and its lines in ``log`` (module doc).

    Args:
        diag: the node's diagnostics.
        log: the node's logger.
        run: the run reported on.
        p: the node's parameters.
    """

    def __init__(self, diag: Diagnostics, log, run: ExcitationRun, p: dict) -> None:
        self.diag, self.log, self.run, self.p = diag, log, run, p
        diag.values.update(signal='waiting for tip_positions', level=p['level'],
                           plan_duration=f'{run.whole.duration:.3f}')
        if run.search is None:
            diag.values.update(amplitude=f'{p["amplitude"]:g}',
                               clip_share=f'{run.plan.clip_share():.4f}')

    def log_start(self, names: tuple[str, ...], source: str) -> None:
        """One line of what will run (``names``: the fingers): the signals, the finger, the
        limit and where it came from (``source``), the level, the timing."""
        p, plan, search = self.p, self.run.plan, self.run.search
        signals = ', '.join(seg.signal.name for seg in self.run.whole.segments)
        where = 'every finger' if p['finger'] < 0 else names[p['finger']]
        level = (f'amplitude {p["amplitude"]:g} ({self._clip_text()})' if search is None else
                 f'amplitude by probes aiming at {1e3 * search.goal:g} mm'
                 + (', each signal its own' if self.run.per_signal is not None else ''))
        within = (f'|u| <= {p["torque_limit"]:g} N·m' if plan.map is None
                  else f'{plan.m} input(s) within {plan.map.bounds}')
        self.log.info(
            f'{signals} on {where} of {len(names)}, '
            f'{p["settle_time"]:g} s settle before each, {within} ({source}), '
            f'{level}, {self.run.whole.duration:g} s in all'
            + (' and the probes' if search is not None else '')
            + f'; {p["timing"]} timing; starting once '
            f'{TORQUE_COMMANDS} has {p["min_command_subscribers"]} subscriber(s)')

    def step(self, step: RunStep) -> None:
        """The run at ``step``: the settle phase's extension, the chosen level, and (unless the
        run is over) the signal, the plan time and the first non-zero torque."""
        settle = self.run.settle
        if settle.extended and settle.shift is not None:
            self.diag.values['settle_extended'] = f'{settle.shift:.3f}'
        if step.level_chosen:
            self._level_chosen()
        if step.phase is Phase.OVER:
            return
        self.diag.values.update(self._status(step))
        if step.first_torque:
            self._first_torque()

    def _status(self, step: RunStep) -> dict[str, str]:
        """The signal (or probe) played at ``step``, the plan time and the probe's level."""
        if step.phase is Phase.SETTLE:
            return dict(signal='settle', plan_time='')
        if step.phase is Phase.PROBE:
            search = self.run.search
            probe = len(search.probes) + 1
            return dict(signal=f'level probe {probe}' if step.t >= search.settle_time else 'settle',
                        level=f'auto: probe {probe} at amplitude {search.current:.4g}',
                        plan_time='')
        seg = self.run.plan.segment_at(step.t)
        return dict(signal=seg.signal.name if seg is not None else 'settle',
                    plan_time=f'{step.t:.3f}')

    def _level_chosen(self) -> None:
        """The amplitude the search chose, its probes and the plan's share at the clip."""
        search = self.run.search
        probes = ', '.join(f'{pr.amplitude:.4g} → {1e3 * pr.excursion:.2f} mm'
                           for pr in search.probes)
        self.diag.values.update(level='auto: chosen', amplitude=f'{search.amplitude:.6g}',
                                clip_share=f'{self.run.plan.clip_share():.4f}', probes=probes)
        if self.run.per_signal is not None:
            name = self.run.plan.segments[0].signal.name
            self.diag.values['levels'] = ', '.join(f'{n} {a:.4g}' for n, a in self.run.levels)
            scaled = ', '.join(f'{r:.3g}' for r in search.ratios)
            self.log.info(f'level of {name}: probes of its first {search.probe_time:g} s '
                          f'(amplitude → peak excursion) {probes}, taken × {scaled} for the '
                          f'whole signal (its measured response); amplitude '
                          f'{search.amplitude:.4g} {self._goal_text()}, {self._clip_text()}')
            self._warn_capped()
            return
        self.log.info(f'level probes (amplitude → peak excursion): {probes}; amplitude '
                      f'{search.amplitude:.4g} {self._goal_text()}, {self._clip_text()}')
        self._warn_capped()

    def _goal_text(self) -> str:
        search = self.run.search
        if not search.capped:
            return f'for {1e3 * search.goal:g} mm'
        return (f'(the largest the input bounds allow) for about {1e3 * search.expected:.2f} mm '
                f'of the {1e3 * search.goal:g} mm aimed at')

    def _warn_capped(self) -> None:
        """A warning when the bounds kept the signal below the aimed excursion."""
        search = self.run.search
        if search.capped:
            self.diag.values['capped'] = f'{1e3 * search.expected:.2f} of {1e3 * search.goal:g} mm'
            self.log.warn(f'the input bounds cap the level: about {1e3 * search.expected:.2f} mm '
                          f'of the {1e3 * search.goal:g} mm aimed at; the recording moves the '
                          'finger less (a lower max_excursion matches it, wider bounds exceed it)')

    def _first_torque(self) -> None:
        """How many zero-torque answers came before the first non-zero torque; a warning when
        they are too few for training to estimate the noise level."""
        settle = self.run.settle
        self.diag.values['settle_tips'] = str(settle.zero_answers)
        extended = (f', settle phase extended by {settle.shift:.3f} s for settle_samples'
                    if settle.extended else '')
        self.log.info(f'first non-zero torque after {settle.zero_answers} tip message(s) '
                      f'answered with zero torque{extended}')
        if settle.zero_answers < MIN_SETTLE_SAMPLES:
            self.log.warn(
                f'only {settle.zero_answers} tip message(s) answered with zero torque before the '
                'first non-zero torque; training estimates the noise level from '
                f'{MIN_SETTLE_SAMPLES} or more (a longer settle_time, or give train --meas-std)')

    def _clip_text(self) -> str:
        plan = self.run.plan
        return (f"{100 * plan.clip_share():.1f} % of the signals' samples at the "
                + ('torque limit' if plan.map is None else 'bounds'))
