"""Excitation torques for identifying one finger (SI: N·m, shape (N, 2) = [u_ax0, u_ax1]).

The paper's four signals (eq. 25, sim units, s = sin, both torques equal):

    u1 = 25 s(πt)                    u2 = 25 s(0.5πt) + 2
    u3 = 10 s(2πt) + 15 s(πt)        u4 = 6 s(3πt) + 7 s(2πt) + 8 s(πt)

Because both torques are always equal, data from u1..u4 cannot tell how the input matrix G2(x)
splits between its two columns: any G2 with the same row sums fits it equally well. The
identification signals ``x1`` and ``x2`` drive the two torques independently — multisines on
disjoint, incommensurate frequency sets per axis, so the two inputs are uncorrelated over the
record and each takes both signs — with peaks inside the paper's ±25 sim-unit range.

**Fingers of m inputs** (1 to 4) with per-input bounds take the same signals as shares of their
intervals (:func:`input_signal`): each signal in sim units divided by :data:`REFERENCE` (40 sim
units, the simulator's 0.1 N·m actuator limit, so u1 peaks at 0.625), for m inputs: u1..u3 the
same on every input, and u4 too for one input or two bidirectional ones; for three or four inputs,
or two that only push or pull, u4 plays on input k the same waveform delayed by k/m of its
period (:data:`U4_PERIOD`, :func:`u4_delays`); x1,
x2 multisines on disjoint, incommensurate frequency sets per input (the hand's two sets, then
two more); b1, b2 the broadband multisine with its 12 frequencies per
input dealt to the inputs in turn (b2 starting one input later; for one input b1 and b2 take
the alternate frequencies of two). The excitation plan maps a share s to an
input about the middle of a two-sided interval, or from the rest value into a one-sided one
(:mod:`soft_gripper_sdre.sim.excitation`). For two inputs the shares are the hand's signals
over 0.1 N·m.

**Why u4 is staggered for more than two inputs.** u4 is the recipe's validation signal. A finger
bends in at most two directions; with more inputs than that, inputs driven alike mostly act
against each other (three tendons at 120° pulled alike shorten a segment and hardly bend it), so
a validation record with every input equal moves the tip little and tests one direction of
input space. Delayed by k/m of the 2 s period, the three components of u4 (0.5, 1 and 1.5 Hz)
reach the inputs at phases 2πjk/m (j = 1, 2, 3): for m = 3 the 0.5 and 1 Hz components sum to
zero over the inputs (a tip that circles) and the 1.5 Hz one stays common to all (the
shortening), for m = 4 none is common. Two inputs that only push or pull are most often a pair
acting against each other (a flexor and an extensor tendon, chambers on opposite sides): played
alike they cancel at the tip, and a validation record of them tests the pair's stiffening and
hardly its motion. Delayed by half the period, u4's 0.5 and 1.5 Hz components drive the pair
against each other (the tip moves) and its 1 Hz one drives both alike (co-contraction, or the
bending of two inputs that act the same way), so the record holds both whatever the pair's
arrangement. Every input plays u4's own values, so its peak and its level are u4's.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from soft_gripper_sdre.sim.units import torque_to_si

#: duration of every excitation record [s] (the paper's 10 000 samples at 1 ms)
DURATION = 10.0


def _equal(f: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """Both torques equal to f(t) (sim units) → (N, 2) N·m."""
    def signal(t):
        t = np.asarray(t, dtype=float)
        v = torque_to_si(f(t))
        return np.stack([v, v], axis=-1)
    return signal


def _multisine(amplitudes_ax0, freqs_ax0, phases_ax0, amplitudes_ax1, freqs_ax1, phases_ax1):
    """Independent multisines per axis (amplitudes in sim units, frequencies in Hz)."""
    def axis(t, amps, freqs, phases):
        return sum(a * np.sin(2 * np.pi * f * t + p) for a, f, p in zip(amps, freqs, phases))

    def signal(t):
        t = np.asarray(t, dtype=float)
        return torque_to_si(np.stack([axis(t, amplitudes_ax0, freqs_ax0, phases_ax0),
                                      axis(t, amplitudes_ax1, freqs_ax1, phases_ax1)], axis=-1))
    return signal


def _broadband(f_lo: float, f_hi: float, per_axis: int, axis0_first: bool, peak: float = 25.0):
    """Independent multisines per axis over [f_lo, f_hi] Hz (sim units): 2·``per_axis``
    log-spaced frequencies dealt alternately to the axes (ax0 the first when ``axis0_first``),
    equal amplitudes, Schroeder phases φ_k = −π k(k−1)/K (a low crest factor), scaled so the
    larger axis peaks at ``peak`` over the record (:data:`DURATION` s at 1 ms)."""
    freqs = np.geomspace(f_lo, f_hi, 2 * per_axis)
    sets = (freqs[0::2], freqs[1::2]) if axis0_first else (freqs[1::2], freqs[0::2])
    k = np.arange(1, per_axis + 1)
    phases = -np.pi * k * (k - 1) / per_axis
    t = np.arange(int(DURATION * 1000)) * 1e-3
    raw = [np.sin(2 * np.pi * f[:, None] * t + phases[:, None]).sum(axis=0) for f in sets]
    amp = peak / max(np.abs(r).max() for r in raw)

    def signal(t):
        t = np.asarray(t, dtype=float)
        axes = [amp * np.sin(2 * np.pi * np.multiply.outer(t, f) + phases).sum(axis=-1)
                for f in sets]
        return torque_to_si(np.stack(axes, axis=-1))
    return signal


s = np.sin
pi = np.pi

#: name → u(t) (N·m, (N, 2)); u1..u4 are the paper's eq. 25, x1/x2 identify G2's columns
SIGNALS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    'u1': _equal(lambda t: 25 * s(pi * t)),
    'u2': _equal(lambda t: 25 * s(0.5 * pi * t) + 2),
    'u3': _equal(lambda t: 10 * s(2 * pi * t) + 15 * s(pi * t)),
    'u4': _equal(lambda t: 6 * s(3 * pi * t) + 7 * s(2 * pi * t) + 8 * s(pi * t)),
    # grasp axis slow and strong, side axis on other frequencies; peaks stay below 25 sim units
    'x1': _multisine((10, 6, 4), (0.3, 0.9, 1.7), (0.0, 1.0, 2.0),
                     (9, 6, 4), (0.5, 1.3, 2.3), (0.5, 2.5, 4.0)),
    # the same idea with the frequency sets swapped between the axes, other phases
    'x2': _multisine((9, 6, 4), (0.5, 1.3, 2.3), (1.5, 0.2, 3.0),
                     (10, 6, 4), (0.3, 0.9, 1.7), (2.0, 4.0, 0.7)),
    # broadband, for fingers faster or stiffer than this one: 0.2 to 30 Hz on both axes, each
    # with its own frequencies (b2 deals them the other way round)
    'b1': _broadband(0.2, 30.0, 12, True),
    'b2': _broadband(0.2, 30.0, 12, False),
}

#: the sim-unit value a share of 1 stands for (the simulator's 0.1 N·m actuator limit)
REFERENCE = 40.0

#: x1 and x2 per input: (amplitudes, frequencies [Hz], phases) in sim units; the hand's two
#: inputs first, then two more on frequencies of their own
_X_AXES = {
    'x1': (((10, 6, 4), (0.3, 0.9, 1.7), (0.0, 1.0, 2.0)),
           ((9, 6, 4), (0.5, 1.3, 2.3), (0.5, 2.5, 4.0)),
           ((9, 6, 4), (0.4, 1.1, 1.9), (1.0, 3.0, 0.3)),
           ((9, 6, 4), (0.7, 1.5, 2.9), (2.2, 0.4, 5.0))),
    'x2': (((9, 6, 4), (0.5, 1.3, 2.3), (1.5, 0.2, 3.0)),
           ((10, 6, 4), (0.3, 0.9, 1.7), (2.0, 4.0, 0.7)),
           ((9, 6, 4), (0.7, 1.5, 2.9), (0.9, 2.1, 4.4)),
           ((9, 6, 4), (0.4, 1.1, 1.9), (3.3, 1.2, 0.1))),
}
_PAPER = {
    'u1': lambda t: 25 * s(pi * t),
    'u2': lambda t: 25 * s(0.5 * pi * t) + 2,
    'u3': lambda t: 10 * s(2 * pi * t) + 15 * s(pi * t),
    'u4': lambda t: 6 * s(3 * pi * t) + 7 * s(2 * pi * t) + 8 * s(pi * t),
}


#: the period of u4 [s] (its components are at 0.5, 1 and 1.5 Hz)
U4_PERIOD = 2.0


def u4_delays(m: int, one_sided: bool = False) -> np.ndarray:
    """The delay [s] of u4 on each of ``m`` inputs (module doc): k·:data:`U4_PERIOD`/m on input
    k for three or four inputs, and for two that only push or pull (``one_sided``); 0 on every
    input otherwise (the hand's u4, both torques equal)."""
    if m == 1 or (m == 2 and not one_sided):
        return np.zeros(m)
    return np.arange(m) * U4_PERIOD / m


def _broadband_shares(f_lo: float, f_hi: float, per_axis: int, m: int, first: int,
                      peak: float = 25.0) -> Callable[[np.ndarray], np.ndarray]:
    """:func:`_broadband` for ``m`` inputs as shares: g·``per_axis`` log-spaced frequencies
    (g = max(m, 2) groups) dealt to the groups in turn, input k taking group k − ``first``
    (mod g), Schroeder phases, scaled so the largest input peaks at ``peak`` sim units over the
    record, over :data:`REFERENCE`. (One input: b1 takes the frequencies b2 leaves.)"""
    groups = max(m, 2)
    freqs = np.geomspace(f_lo, f_hi, groups * per_axis)
    sets = [freqs[(k - first) % groups::groups] for k in range(m)]
    k = np.arange(1, per_axis + 1)
    phases = -np.pi * k * (k - 1) / per_axis
    t = np.arange(int(DURATION * 1000)) * 1e-3
    raw = [np.sin(2 * np.pi * f[:, None] * t + phases[:, None]).sum(axis=0) for f in sets]
    amp = peak / max(np.abs(r).max() for r in raw) / REFERENCE

    def signal(t):
        t = np.asarray(t, dtype=float)
        return np.stack([amp * np.sin(2 * np.pi * np.multiply.outer(t, f) + phases).sum(axis=-1)
                         for f in sets], axis=-1)
    return signal


def input_signal(name: str, m: int, one_sided: bool = False) -> Callable[[np.ndarray], np.ndarray]:
    """The built-in signal ``name`` for ``m`` inputs as shares of each input's interval: t (N,)
    [s] → (N, m), within ±1 (module doc); ``one_sided``: every input only pushes or only pulls
    (u4 is then staggered for two inputs too, :func:`u4_delays`).

    Raises:
        KeyError: unknown name (the message lists the known ones).
        ValueError: ``m`` not 1 to 4.
    """
    get_signal(name)
    if not (isinstance(m, (int, np.integer)) and 1 <= m <= 4):
        raise ValueError(f'the number of inputs m must be 1 to 4, got {m!r}')
    delays = u4_delays(m, one_sided) if name == 'u4' else np.zeros(m)
    if delays.any():
        f = _PAPER[name]

        def staggered(t):
            t = np.asarray(t, dtype=float)
            return f(np.subtract.outer(t, delays)) / REFERENCE
        return staggered
    if name in _PAPER:
        f = _PAPER[name]

        def paper(t):
            v = f(np.asarray(t, dtype=float)) / REFERENCE
            return np.stack([v] * m, axis=-1)
        return paper
    if name in _X_AXES:
        axes = _X_AXES[name][:m]

        def multisine(t):
            t = np.asarray(t, dtype=float)
            return np.stack([sum(a * np.sin(2 * np.pi * f * t + p) for a, f, p in zip(*axis))
                             for axis in axes], axis=-1) / REFERENCE
        return multisine
    return _broadband_shares(0.2, 30.0, 12, m, 0 if name == 'b1' else 1)


PAPER_SIGNALS = ('u1', 'u2', 'u3', 'u4')
IDENTIFYING_SIGNALS = ('x1', 'x2')
BROADBAND_SIGNALS = ('b1', 'b2')


def signal_names() -> list[str]:
    """Every known signal name."""
    return list(SIGNALS)


def get_signal(name: str) -> Callable[[np.ndarray], np.ndarray]:
    """The signal called ``name``.

    Raises:
        KeyError: unknown name (the message lists the known ones).
    """
    try:
        return SIGNALS[name]
    except KeyError:
        raise KeyError(f'unknown signal {name!r}; known signals: {", ".join(SIGNALS)}') from None
