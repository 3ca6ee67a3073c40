"""Identification runs as a schedule of torques: which torque each finger gets at each instant.

An :class:`ExcitationPlan` plays a list of :class:`Signal` one after the other, each after a
settle phase at zero torque, on one finger or on all of them, scaled by an amplitude and then
clipped to a torque limit; after the last signal every torque is zero. The excitation node's
run (:class:`~soft_gripper_sdre.sim.excitation_run.ExcitationRun`) asks
:meth:`ExcitationPlan.torques` for the torque at the plan's time. :meth:`ExcitationPlan.clip_share`
says how much of the signals sits on the clip at an amplitude.

A :class:`LevelSearch` chooses the amplitude on the finger itself, before the plan: after a
settle phase (the rest pose) it plays short probes at amplitudes rising geometrically, each
followed by a settle phase, measures each probe's peak excursion from rest, and stops once a
probe moves the tip to near a target distance; the amplitude then scales the signals to that
target, assuming a roughly linear response (see the class).

**The level per signal.** One amplitude for every signal leaves the weaker or faster signals
short of the target (and a sine probe at the signals' peak says little about a multisine's
response). A search can instead level one signal (:meth:`ExcitationPlan.signal_plan`) with
probes made of the signal itself (:meth:`ExcitationPlan.own_probe`, :class:`SignalProbe`): its
first ``probe_time`` seconds. A signal's strongest response may come later than its start (slow
components adding up), so each probe's excursion is scaled by the signal's measured response:
a second-order ARX model per tip coordinate fit on the probe's own record (inputs and tips)
predicts the whole signal's peak excursion over the probe's
(:meth:`SignalProbe.response_ratio`, within [1, :data:`MAX_RATIO`]); where the fit is unstable
or degenerate, the ratio of the signal's peak input swing to the probe's stands in.

The signals are the built-in ones or those of a YAML file
(:mod:`soft_gripper_sdre.sim.signal_specs`).

**Inputs with bounds.** Without ``bounds`` a plan drives the hand's two torques, clipped to
±``torque_limit``. With ``bounds`` (:class:`~soft_gripper_sdre.sim.shape.InputBounds`, m
inputs) each input k gets, at amplitude a,

    u_k = b_k + a (o_k + g_k s_k(t)),   clipped to [lower_k, upper_k],

where s is the signal: for a built-in one the share of the interval (``Signal.share``,
:func:`~soft_gripper_sdre.sim.signals.input_signal`), with b_k the middle of a two-sided
interval (o_k = 0, g_k its half-width), or for a one-sided input (a chamber, a tendon) its rest
value, the bound nearest zero, and o_k = ±g_k = ±half the width toward the interval: the
input moves from its rest value into the interval, never past it; for a spec file's signal the
input itself (b = o = 0, g = 1). Settling and after the end, and on the fingers not excited,
each input holds its rest value.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np

from soft_gripper_sdre.sim.shape import InputBounds
from soft_gripper_sdre.sim.signal_specs import Signal

#: rate [Hz] at which the signals are sampled for their peaks and their share at the clip
SAMPLE_RATE = 1000.0


# -- the schedule ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Segment:
    """One signal of a plan: it runs over [start, start + duration) of plan time, after its
    settle."""

    signal: Signal
    start: float

    @property
    def end(self) -> float:
        return self.start + self.signal.duration


class InputMap:
    """How a plan turns a signal into inputs (module doc): u = b + a (o + g ∘ s), clipped.

    Args:
        bounds: the inputs' intervals.
    """

    def __init__(self, bounds: InputBounds) -> None:
        self.bounds = bounds
        self.m = bounds.m
        self.rest = bounds.rest
        one = bounds.one_sided
        toward = np.where(bounds.upper > 0, 1.0, -1.0)      # a one-sided input's interval
        self.share_base = np.where(one, self.rest, bounds.mid)
        self.share_gain = np.where(one, 0.5 * (bounds.upper - bounds.lower), bounds.half_span)
        self.share_offset = np.where(one, toward * self.share_gain, 0.0)

    def terms(self, signal: Signal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(b, o, g) (m,) for ``signal``."""
        if signal.share:
            return self.share_base, self.share_offset, self.share_gain
        return np.zeros(self.m), np.zeros(self.m), np.ones(self.m)

    def inputs(self, signal: Signal, s: np.ndarray, amplitude: float) -> np.ndarray:
        """The inputs (…, m) for the signal's values ``s`` (…, m) at ``amplitude``, clipped."""
        b, o, g = self.terms(signal)
        return self.bounds.clip(b + amplitude * (o + g * s))


class ExcitationPlan:
    """Settle, signal, settle, signal, … then zero torque (module doc).

    Args:
        signals: played in this order.
        settle_time: zero torque (the rest inputs) before each signal [s].
        n_fingers: the torque is (n_fingers, 2), or (n_fingers, m) with ``bounds``.
        finger: the finger that is excited (None: all); the others get zero (the rest inputs).
        torque_limit: each torque is clipped to ±torque_limit [N·m] (without ``bounds``).
        amplitude: each signal's torque is multiplied by this before the clip.
        bounds: the m inputs' intervals (module doc); None: the hand's ±torque_limit on two.

    Raises:
        ValueError: no signals, or a bad settle time, finger, limit or amplitude, or a signal
            for another number of inputs.
    """

    def __init__(self, signals: Sequence[Signal], settle_time: float, n_fingers: int,
                 finger: int | None = None, torque_limit: float = 0.1,
                 amplitude: float = 1.0, bounds: InputBounds | None = None) -> None:
        if not signals:
            raise ValueError('an excitation plan needs at least one signal')
        if not (math.isfinite(settle_time) and settle_time >= 0):
            raise ValueError(f'settle_time must be finite and >= 0 s, got {settle_time!r}')
        if not 1 <= n_fingers <= 4:
            raise ValueError(f'n_fingers must be in [1, 4], got {n_fingers!r}')
        if finger is not None and not 0 <= finger < n_fingers:
            raise ValueError(f'finger must be in [0, {n_fingers - 1}] (or all), got {finger!r}')
        if not (math.isfinite(torque_limit) and torque_limit > 0):
            raise ValueError(f'torque_limit must be finite and > 0 N·m, got {torque_limit!r}')
        if not (math.isfinite(amplitude) and amplitude > 0):
            raise ValueError(f'amplitude must be finite and > 0, got {amplitude!r}')
        self.n_fingers = n_fingers
        self.finger = finger
        #: the inputs' map (None: the hand's torques) and their number
        self.map = None if bounds is None else InputMap(bounds)
        self.m = 2 if bounds is None else bounds.m
        self.rest = np.zeros(2) if bounds is None else self.map.rest
        if self.map is not None:
            for signal in signals:
                got = np.shape(signal.torque(np.zeros(1)))
                if got != (1, self.m):
                    raise ValueError(f'signal {signal.name!r} gives {got[-1]} input(s); the '
                                     f'finger has {self.m}')
        self.torque_limit = float(torque_limit)
        self.amplitude = float(amplitude)
        self.settle_time = float(settle_time)
        segments, t = [], 0.0
        for signal in signals:
            t += settle_time
            segments.append(Segment(signal, t))
            t += signal.duration
        self.segments = tuple(segments)
        self.duration = t
        self._samples: tuple[np.ndarray, np.ndarray] | None = None

    def scaled(self, amplitude: float) -> 'ExcitationPlan':
        """The same plan with the signals multiplied by ``amplitude`` (instead of this one's).

        Raises:
            ValueError: ``amplitude`` is not finite and > 0.
        """
        if not (math.isfinite(amplitude) and amplitude > 0):
            raise ValueError(f'amplitude must be finite and > 0, got {amplitude!r}')
        plan = copy.copy(self)
        plan.amplitude = float(amplitude)
        return plan

    def _sampled(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis peak |torque| (2,) of the signals at amplitude 1, unclipped, and each
        sample's larger |torque| of the two axes, the signals sampled at :data:`SAMPLE_RATE`.
        With bounds: every sample's b and o + g ∘ s (N, m) (module doc)."""
        if self._samples is None and self.map is not None:
            base, swing = [], []
            for seg in self.segments:
                n = max(1, int(math.ceil(seg.signal.duration * SAMPLE_RATE)))
                s = seg.signal.torque(np.arange(n) / SAMPLE_RATE)
                b, o, g = self.map.terms(seg.signal)
                swing.append(o + g * np.where(np.isfinite(s), s, 0.0))
                base.append(np.broadcast_to(b, swing[-1].shape))
            self._samples = (np.concatenate(base), np.concatenate(swing))
        if self._samples is None:
            peak, larger = np.zeros(2), []
            for seg in self.segments:
                n = max(1, int(math.ceil(seg.signal.duration * SAMPLE_RATE)))
                t = np.arange(n) / SAMPLE_RATE
                u = np.abs(seg.signal.torque(t))
                u = np.where(np.isfinite(u), u, 0.0)
                peak = np.maximum(peak, u.max(axis=0))
                larger.append(u.max(axis=1))
            self._samples = (peak, np.concatenate(larger))
        return self._samples

    @property
    def peak_torque(self) -> np.ndarray:
        """The signals' largest |torque| per axis (2,) [N·m] at amplitude 1, before the clip
        (with bounds: the largest |o + g ∘ s| per input (m,))."""
        if self.map is not None:
            return np.abs(self._sampled()[1]).max(axis=0)
        return self._sampled()[0].copy()

    def clip_share(self, amplitude: float | None = None) -> float:
        """The share of the signals' samples (at :data:`SAMPLE_RATE`, settle phases left out)
        at the clip, on either axis, at ``amplitude`` (default: the plan's)."""
        a = self.amplitude if amplitude is None else float(amplitude)
        if self.map is not None:
            base, swing = self._sampled()
            u = base + a * swing
            out = (u > self.map.bounds.upper) | (u < self.map.bounds.lower)
            return float(np.count_nonzero(out.any(axis=1)) / len(u))
        larger = self._sampled()[1]
        return float(np.count_nonzero(a * larger >= self.torque_limit) / larger.size)

    def largest_unclipped_amplitude(self) -> float:
        """The amplitude at which the signals' peak just reaches the torque limit, or with
        bounds the first bound (inf: the signals are zero)."""
        if self.map is not None:
            base, swing = self._sampled()
            room = np.where(swing > 0, self.map.bounds.upper - base,
                            np.where(swing < 0, self.map.bounds.lower - base, np.inf))
            with np.errstate(divide='ignore', invalid='ignore'):
                limits = np.where(swing != 0, room / swing, np.inf)
            return float(max(0.0, limits.min()))
        peak = float(self._sampled()[0].max())
        return self.torque_limit / peak if peak > 0 else math.inf

    def segment_at(self, t: float) -> Segment | None:
        """The segment whose signal runs at plan time ``t`` (None: settling or finished)."""
        for seg in self.segments:
            if seg.start <= t < seg.end:
                return seg
        return None

    def finished(self, t: float) -> bool:
        """Whether plan time ``t`` lies past the last signal."""
        return t >= self.duration

    def rest_inputs(self) -> np.ndarray:
        """(n_fingers, m) every input at rest: zero torque, a vented chamber, a slack tendon."""
        return np.tile(self.rest, (self.n_fingers, 1))

    def torques(self, t: float) -> np.ndarray:
        """The (n_fingers, 2) torque at plan time ``t`` [s] (zero while settling and after the
        end); with bounds (n_fingers, m) inputs (the rest inputs then)."""
        if self.map is not None:
            return self._inputs(t)
        u = np.zeros((self.n_fingers, 2))
        seg = self.segment_at(t)
        if seg is None:
            return u
        value = seg.signal.torque(np.array([t - seg.start]))[0]
        value = np.where(np.isfinite(value), value, 0.0) * self.amplitude
        value = np.clip(value, -self.torque_limit, self.torque_limit)
        if self.finger is None:
            u[:] = value
        else:
            u[self.finger] = value
        return u

    def _inputs(self, t: float) -> np.ndarray:
        u = self.rest_inputs()
        seg = self.segment_at(t)
        if seg is None:
            return u
        s = seg.signal.torque(np.array([t - seg.start]))[0]
        value = self.map.inputs(seg.signal, np.where(np.isfinite(s), s, 0.0), self.amplitude)
        if self.finger is None:
            u[:] = value
        else:
            u[self.finger] = value
        return u

    def signal_plan(self, j: int) -> 'ExcitationPlan':
        """The plan of signal ``j`` alone: its settle phase, then the signal (the same fingers,
        limit, amplitude and bounds)."""
        plan = copy.copy(self)
        plan.segments = (Segment(self.segments[j].signal, self.settle_time),)
        plan.duration = self.settle_time + self.segments[j].signal.duration
        plan._samples = None
        return plan

    def own_probe(self, probe_time: float) -> 'SignalProbe':
        """The probe of a :class:`LevelSearch` that plays this plan's first signal itself: its
        first ``probe_time`` seconds (class doc of :class:`SignalProbe`).

        Raises:
            ValueError: the signal is zero over the probe, or the plan has no room for it.
        """
        sig = self.segments[0].signal
        n = max(1, int(math.ceil(sig.duration * SAMPLE_RATE)))
        s = sig.torque(np.arange(n) / SAMPLE_RATE)
        s = np.where(np.isfinite(s), s, 0.0)
        if self.map is None:
            swing = np.abs(s)
        else:
            _, o, g = self.map.terms(sig)
            swing = np.abs(o + g * s)
        head = swing[:max(1, int(math.ceil(min(probe_time, sig.duration) * SAMPLE_RATE)))]
        if not head.max() > 0:
            raise ValueError(f'signal {sig.name!r} is zero over its first {probe_time:g} s: '
                             'it cannot probe its own level')
        largest = self.largest_unclipped_amplitude()
        if not 0 < largest < math.inf:
            raise ValueError(f'signal {sig.name!r} has no room within the limit')
        return SignalProbe(self, float(swing.max() / head.max()), largest)

    def probe_inputs(self) -> 'ProbeInputs':
        """What a :class:`LevelSearch` probes with for this plan's bounds (module doc, class
        doc): the first signal's b and o, its peak swing g ∘ max|s| per input and the largest
        unclipped amplitude.

        Raises:
            ValueError: no bounds, or signals of both kinds (built-in shares and a spec file's
                inputs), whose probes would differ.
        """
        if self.map is None:
            raise ValueError('probe inputs need a plan with bounds')
        kinds = {seg.signal.share for seg in self.segments}
        if len(kinds) > 1:
            raise ValueError('level auto with input bounds needs the signals all built-in or '
                             'all from spec_file')
        first = self.segments[0].signal
        b, o, g = self.map.terms(first)
        _, swing = self._sampled()
        peak = np.abs(swing - o).max(axis=0)
        return ProbeInputs(self.map.bounds, b, o, peak, self.largest_unclipped_amplitude())


@dataclass(frozen=True)
class ProbeInputs:
    """A :class:`LevelSearch`'s probe on bounded inputs: at amplitude a and pattern w (m,)
    in [−1, 1], u = clip(base + a (offset + swing ∘ w)); ``largest`` is the amplitude the
    search does not exceed."""

    bounds: InputBounds
    base: np.ndarray
    offset: np.ndarray
    swing: np.ndarray
    largest: float


#: the most a signal's measured response may scale its probe's excursion
MAX_RATIO = 4.0


def _arx_response(a1: float, a2: float, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """y_k = a1 y_{k−1} + a2 y_{k−2} + b[0] · x_{k−1} + b[1] · x_{k−2} from rest, for the inputs
    ``x`` (N, m); ``b`` (2, m)."""
    drive = np.zeros(len(x))
    drive[1:] += x[:-1] @ b[0]
    drive[2:] += x[:-2] @ b[1]
    y = [0.0, 0.0]
    for v in drive.tolist():
        y.append(a1 * y[-1] + a2 * y[-2] + v)
    return np.array(y[2:])


@dataclass(frozen=True)
class SignalProbe:
    """A :class:`LevelSearch`'s probe made of the signal it levels: the single-signal ``plan``'s
    signal from its start, at the probe's amplitude (clipped as the plan clips). A signal's
    strongest moment may come after the probe: ``correction`` (>= 1) is the signal's peak over
    its peak within the probe (|s| for the hand's torques, |o + g ∘ s| for bounded inputs), the
    quasi-static scaling the search takes a probe's excursion times when
    :meth:`response_ratio` has no answer. ``largest`` is the amplitude at which the signal
    reaches the limit (the search does not exceed it)."""

    plan: 'ExcitationPlan'
    correction: float
    largest: float

    def signal_inputs(self, times: np.ndarray, amplitude: float) -> np.ndarray:
        """The torques or inputs (N, m) of the whole signal at ``times`` (N,) [s] and
        ``amplitude``, as the plan plays them."""
        plan, sig = self.plan, self.plan.segments[0].signal
        value = sig.torque(np.asarray(times, dtype=float))
        value = np.where(np.isfinite(value), value, 0.0)
        if plan.map is not None:
            return plan.map.inputs(sig, value, amplitude)
        return np.clip(value * amplitude, -plan.torque_limit, plan.torque_limit)

    def response_ratio(self, times: np.ndarray, moved: np.ndarray, inputs: np.ndarray,
                       amplitude: float) -> float | None:
        """The signal's measured response (module doc): from one probe's record, the tip's
        displacement ``moved`` (N, 3) [m] from rest and the inputs (N, m) applied at ``times``
        (N,) [s], fit y_k = a1 y_{k−1} + a2 y_{k−2} + B1 x_{k−1} + B2 x_{k−2} per coordinate (x:
        the inputs from rest) and return the peak |y| it predicts for the whole signal at
        ``amplitude`` over the peak it predicts for the probe, within [1, :data:`MAX_RATIO`];
        None when the record is too short or the fit is unstable or degenerate."""
        times, moved, inputs = (np.asarray(v, dtype=float) for v in (times, moved, inputs))
        if len(times) < 30 or not (np.all(np.isfinite(moved)) and np.all(np.isfinite(inputs))):
            return None
        dt = float(np.median(np.diff(times)))
        if not dt > 0:
            return None
        rest = self.plan.rest
        x = inputs - rest
        grid = np.arange(0.0, self.plan.segments[0].signal.duration, dt)
        x_full = self.signal_inputs(grid, amplitude) - rest
        full, probe = np.zeros((len(grid), 3)), np.zeros((len(x), 3))
        for c in range(3):
            y = moved[:, c]
            if not np.ptp(y) > 0:
                continue
            reg = np.column_stack([y[1:-1], y[:-2], x[1:-1], x[:-2]])
            coef, *_ = np.linalg.lstsq(reg, y[2:], rcond=None)
            a1, a2, b = coef[0], coef[1], coef[2:].reshape(2, -1)
            if not (np.all(np.isfinite(coef)) and np.all(np.abs(np.roots([1.0, -a1, -a2])) < 1)):
                return None
            full[:, c] = _arx_response(a1, a2, b, x_full)
            probe[:, c] = _arx_response(a1, a2, b, x)
        seen = float(np.linalg.norm(probe, axis=1).max())
        if not seen > 0:
            return None
        ratio = float(np.linalg.norm(full, axis=1).max()) / seen
        return min(max(ratio, 1.0), MAX_RATIO) if math.isfinite(ratio) else None

    def inputs(self, s: float, amplitude: float) -> np.ndarray:
        """The torque (2,) or inputs (m,) at ``s`` seconds into the signal at ``amplitude``."""
        plan, seg = self.plan, self.plan.segments[0]
        value = seg.signal.torque(np.array([s]))[0]
        value = np.where(np.isfinite(value), value, 0.0)
        if plan.map is not None:
            return plan.map.inputs(seg.signal, value, amplitude)
        return np.clip(value * amplitude, -plan.torque_limit, plan.torque_limit)


# -- choosing the amplitude ------------------------------------------------------------------

@dataclass(frozen=True)
class Probe:
    """One probe of a :class:`LevelSearch`: its amplitude, when it started (search time [s]) and
    the peak excursion of an excited tip from rest during it and the settle after it [m]."""

    amplitude: float
    start: float
    excursion: float


@dataclass(frozen=True)
class LevelSettings:
    """How a :class:`LevelSearch` probes and when it stops (its doc uses these names); the search
    checks them.

    Attributes:
        target: the goal as a share of the largest excursion, in (0, 1].
        start: the first probe's amplitude a_0.
        ratio: the most an amplitude grows from one probe to the next (> 1).
        probe_time: the duration of a probe [s].
        settle_time: the zero torque before the first probe and after each [s].
        close: a probe whose excursion is at least this share of the goal ends the search.
    """

    target: float = 0.5
    start: float = 0.05
    ratio: float = 2.0
    probe_time: float = 2.0
    settle_time: float = 0.5
    close: float = 0.8


class LevelSearch:
    """Choose the signals' amplitude from probes on the finger (module doc).

    Search time 0 is the start. Over [0, settle_time) the torque is zero and the excited tips'
    mean is the rest pose. Then probe k runs for ``probe_time`` at amplitude a_k and is followed
    by ``settle_time`` of zero torque; its excursion e_k is the largest distance of an excited tip
    from rest over both. A probe is the signals' peak torque per axis, ``peak``, times a_k times a
    sine of two periods, the axes in phase over the first and in opposite phase over the second,
    so both axes reach their peaks with either relative sign. With bounded inputs
    (``inputs``, :class:`ProbeInputs`) the probe is base + a (offset + swing ∘ w) clipped, w
    the same sine on every input over the first period and of alternating sign from input to
    input over the second, and the largest amplitude is ``inputs.largest`` (``peak`` and
    ``torque_limit`` are not used then). With ``signal`` (:class:`SignalProbe`) the probe is the
    signal being levelled itself, its first ``probe_time`` seconds at a_k (the level per
    signal), each probe's excursion is taken times the signal's measured response
    (:meth:`SignalProbe.response_ratio` on the probe's record of inputs and tips, else
    ``signal.correction``; ``ratios``) and the largest amplitude is ``signal.largest``
    (``peak``, ``torque_limit`` and ``inputs`` are not used then).

    With the goal g = ``target`` × ``max_excursion``: a_0 = ``start``; after a probe with
    e_k ≥ ``close`` × g, or at the largest amplitude (the signals' peak at the torque limit),
    the search ends; otherwise a_{k+1} = min(``ratio`` a_k, a_k g / e_k, largest). The chosen
    amplitude is a_k g / e_k, at most ``ratio`` a_k and at most the largest amplitude, so the
    signals stay off the clip. ``target``, ``start``, ``ratio``, ``probe_time``, ``settle_time``
    and ``close`` are the ``settings`` (:class:`LevelSettings`).

    Drive it with :meth:`step` for each tip message (or each tick, with the newest tips);
    ``done`` then ``amplitude`` and ``end`` (the search time at which it ended) give the result.

    Raises:
        ValueError: a bad argument or setting (named).
    """

    def __init__(self, peak: np.ndarray, torque_limit: float, max_excursion: float,
                 n_fingers: int, finger: int | None = None,
                 settings: LevelSettings = LevelSettings(),
                 inputs: ProbeInputs | None = None, signal: SignalProbe | None = None) -> None:
        self.inputs = inputs
        self.signal = signal
        self.correction = 1.0 if signal is None else float(signal.correction)
        if signal is not None:          # the signal's own scale: peak and torque_limit unused
            m = signal.plan.m
            inputs = None
            self._signal_rest = signal.plan.rest.copy()
            peak, torque_limit = np.ones(2), signal.largest
            if not (math.isfinite(self.correction) and self.correction >= 1):
                raise ValueError(f'signal probe correction must be finite and >= 1, got '
                                 f'{self.correction!r}')
        elif inputs is not None:        # the probe's own scale: peak and torque_limit unused
            if not (0 < inputs.largest < math.inf and inputs.swing.max() > 0):
                raise ValueError('the signals must move the inputs and have room within their '
                                 f'bounds (largest amplitude {inputs.largest!r})')
            peak, torque_limit = np.ones(2), inputs.largest
        peak = np.asarray(peak, dtype=float)
        s = settings
        checks = (
            ('peak', peak.shape == (2,) and bool(np.all(np.isfinite(peak)))
             and bool(np.all(peak >= 0)) and bool(peak.max() > 0),
             'two finite torques >= 0 [N·m], not both zero'),
            ('torque_limit', math.isfinite(torque_limit) and torque_limit > 0,
             'finite and > 0 N·m'),
            ('max_excursion', math.isfinite(max_excursion) and max_excursion > 0,
             'finite and > 0 m'),
            ('target', 0 < s.target <= 1, 'in (0, 1]'),
            ('start', math.isfinite(s.start) and s.start > 0, 'finite and > 0'),
            ('ratio', math.isfinite(s.ratio) and s.ratio > 1, 'finite and > 1'),
            ('probe_time', math.isfinite(s.probe_time) and s.probe_time > 0, 'finite and > 0 s'),
            ('settle_time', math.isfinite(s.settle_time) and s.settle_time > 0,
             'finite and > 0 s'),
            ('close', 0 < s.close <= 1, 'in (0, 1]'),
        )
        for name, ok, what in checks:
            if not ok:
                raise ValueError(f'{name} must be {what}')
        if finger is not None and not 0 <= finger < n_fingers:
            raise ValueError(f'finger must be in [0, {n_fingers - 1}] (or all), got {finger!r}')
        self.peak = peak
        self.n_fingers = n_fingers
        self.rows = list(range(n_fingers)) if finger is None else [finger]
        self.goal = float(s.target) * float(max_excursion)
        self.largest = float(torque_limit) / float(peak.max())
        m = 2 if inputs is None else inputs.bounds.m
        self._rest = np.zeros(2) if inputs is None else inputs.bounds.rest
        if signal is not None:
            m, self._rest = signal.plan.m, self._signal_rest
        self._alternate = np.array([1.0, -1.0]) if inputs is None else (-1.0) ** np.arange(m)
        self.ratio, self.close = float(s.ratio), float(s.close)
        self.probe_time, self.settle_time = float(s.probe_time), float(s.settle_time)
        self.probes: list[Probe] = []
        #: per probe the factor its excursion was taken times (the signal's response, 1 without)
        self.ratios: list[float] = []
        self._record: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.rest: np.ndarray | None = None
        self.amplitude: float | None = None
        self.end: float | None = None
        #: the peak excursion expected at ``amplitude`` (the last probe's, scaled linearly) [m]
        self.expected: float | None = None
        #: the goal needed more than the largest amplitude (the clip or the bounds) allow
        self.capped = False
        self._rest_sum = np.zeros((len(self.rows), 3))
        self._rest_n = 0
        self._a = min(float(s.start), self.largest)
        self._start = self.settle_time          # search time of the current probe's start
        self._excursion = 0.0

    @property
    def done(self) -> bool:
        return self.amplitude is not None

    @property
    def current(self) -> float:
        """The amplitude of the probe running (or the next one)."""
        return self._a

    def probe_torque(self, s: float, amplitude: float) -> np.ndarray:
        """A probe's torque (2,) [N·m] at ``s`` seconds from its start (zero outside it); with
        bounded inputs the inputs (m,) (the rest inputs outside it)."""
        if not 0 <= s < self.probe_time:
            return self._rest.copy()
        if self.signal is not None:
            return self.signal.inputs(s, amplitude)
        w = math.sin(4 * math.pi * s / self.probe_time)
        if self.inputs is None:
            return amplitude * self.peak * np.array([w, w if s < self.probe_time / 2 else -w])
        pattern = w if s < self.probe_time / 2 else w * self._alternate
        p = self.inputs
        return p.bounds.clip(p.base + amplitude * (p.offset + p.swing * pattern))

    def rest_inputs(self) -> np.ndarray:
        """(n_fingers, m) every input at rest."""
        return np.tile(self._rest, (self.n_fingers, 1))

    def step(self, t: float, tips: np.ndarray) -> np.ndarray:
        """Take the tips (n_fingers, 3) [m] measured at search time ``t`` [s]; return the
        torque (n_fingers, 2) [N·m] to apply now (zero once done; with bounded inputs (n, m),
        the rest inputs)."""
        u = self.rest_inputs()
        if self.done:
            return u
        rows = np.asarray(tips, dtype=float)[self.rows, :3]
        if t < self.settle_time:
            if np.all(np.isfinite(rows)):
                self._rest_sum += rows
                self._rest_n += 1
            return u
        if self.rest is None:
            self.rest = self._rest_sum / self._rest_n if self._rest_n else rows.copy()
        if t >= self._start + self.probe_time + self.settle_time:
            self._finish_probe()
            if self.done:
                return u
        d = np.linalg.norm(rows - self.rest, axis=-1)
        self._excursion = max(self._excursion, float(d.max()) if np.all(np.isfinite(d)) else 0.0)
        u[self.rows] = self.probe_torque(t - self._start, self._a)
        if self.signal is not None:
            self._record.append((t, rows - self.rest, u[self.rows[0]].copy()))
        return u

    def _finish_probe(self) -> None:
        ratio = None
        if self.signal is not None and self._record:
            times = np.array([r[0] for r in self._record])
            moved = np.array([r[1] for r in self._record])           # (N, rows, 3)
            row = int(np.argmax(np.nanmax(np.linalg.norm(moved, axis=-1), axis=0)))
            ratio = self.signal.response_ratio(times, moved[:, row],
                                               np.array([r[2] for r in self._record]), self._a)
            self._record = []
        self.ratios.append(self.correction if ratio is None else ratio)
        a, e = self._a, self._excursion * self.ratios[-1]
        self.probes.append(Probe(a, self._start, self._excursion))
        self._start += self.probe_time + self.settle_time
        self._excursion = 0.0
        if e >= self.close * self.goal or a >= self.largest * (1 - 1e-9):
            chosen = a * self.ratio if e <= 0 else a * self.goal / e
            self.amplitude = min(chosen, a * self.ratio, self.largest)
            self.expected = e * self.amplitude / a
            self.capped = min(chosen, a * self.ratio) > self.largest * (1 + 1e-9)
            self.end = self._start
        else:
            grow = a * self.ratio if e <= 0 else min(a * self.ratio, a * self.goal / e)
            self._a = min(grow, self.largest)
