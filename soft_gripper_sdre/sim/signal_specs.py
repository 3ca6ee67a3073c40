"""Excitation signals by name, as :class:`Signal` records for
:class:`~soft_gripper_sdre.sim.excitation.ExcitationPlan`: the built-in ones of
:mod:`soft_gripper_sdre.sim.signals` (the paper's u1..u4 and the identifying x1, x2), or multisines
and chirps defined in a YAML file (``spec_file``; SI: N·m, Hz, rad, s)::

    signals:
      slow_sines:
        kind: multisine
        duration: 10.0
        ax0: {amplitudes: [0.02, 0.01], frequencies: [0.3, 1.1], phases: [0.0, 1.0]}
        ax1: {amplitudes: [0.015], frequencies: [0.7], offset: 0.002}
      sweep:
        kind: chirp
        duration: 8.0
        ax0: {amplitude: 0.03, f0: 0.1, f1: 4.0}                   # linear sweep f0 → f1
        ax1: {amplitude: 0.02, f0: 4.0, f1: 0.2, method: logarithmic}

An axis left out gets zero torque. :func:`load_signal_specs` checks every field and names the
first wrong one (file, signal, axis, field) in a :class:`SignalSpecError`.

For a finger of m inputs (``m``, 1 to 4) the axes are ax0 … ax<m−1>, each in its input's unit
(N·m, Pa, N; amplitudes and offsets up to ``limit``), and the built-in signals are shares of
each input's interval (:func:`~soft_gripper_sdre.sim.signals.input_signal`, ``Signal.share``),
which the excitation plan maps into the bounds; without ``m``, the hand's two torques.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
import re
from typing import Any, Callable, Sequence

import numpy as np
import yaml

from soft_gripper_sdre.sim.signals import DURATION, SIGNALS, input_signal

AXES = ('ax0', 'ax1')
KINDS = ('multisine', 'chirp')
CHIRP_METHODS = ('linear', 'logarithmic')
#: limits of a user-defined signal: length [s], frequency [Hz], amplitude or offset [N·m]
MAX_DURATION = 3600.0
MAX_FREQUENCY = 500.0
MAX_TORQUE = 10.0
_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')

TorqueFunction = Callable[[np.ndarray], np.ndarray]


class SignalSpecError(ValueError):
    """A signal specification cannot be used; the message names the file, signal and field."""


@dataclass(frozen=True)
class Signal:
    """A named excitation: ``torque(t)`` maps times (N,) [s] from its start to torques (N, 2)
    [N·m], or to (N, m) inputs in their units; with ``share`` to (N, m) shares of each input's
    interval (a built-in signal for m inputs)."""

    name: str
    duration: float
    torque: TorqueFunction
    share: bool = False


def builtin_signal(name: str, duration: float | None = None, m: int | None = None,
                   one_sided: bool = False) -> Signal:
    """The built-in signal ``name`` (u1..u4, x1, x2, b1, b2), ``duration`` long (default 10 s):
    the hand's torques, or with ``m`` the shares for m inputs (``one_sided``: every input only
    pushes or only pulls, :func:`~soft_gripper_sdre.sim.signals.input_signal`).

    Raises:
        KeyError: unknown name (the message lists the known ones).
    """
    if name not in SIGNALS:
        raise KeyError(f'unknown signal {name!r}; built-in signals: {", ".join(SIGNALS)}')
    duration = DURATION if duration is None else float(duration)
    if m is None:
        return Signal(name, duration, SIGNALS[name])
    return Signal(name, duration, input_signal(name, m, one_sided), share=True)


# -- user-defined signals --------------------------------------------------------------------

def _number(value: Any, where: str, low: float, high: float, *, open_low: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SignalSpecError(f'{where} must be a finite number, got {value!r}')
    if value < low or value > high or (open_low and value == low):
        bound = f'> {low:g}' if open_low else f'>= {low:g}'
        raise SignalSpecError(f'{where} must be {bound} and <= {high:g}, got {value!r}')
    return float(value)


def _numbers(value: Any, where: str, low: float, high: float, *,
             open_low: bool = False) -> list[float]:
    if not isinstance(value, list) or not value:
        raise SignalSpecError(f'{where} must be a non-empty list of numbers, got {value!r}')
    return [_number(v, f'{where}[{i}]', low, high, open_low=open_low) for i, v in enumerate(value)]


def _fields(block: Any, where: str, required: tuple[str, ...], optional: tuple[str, ...]) -> dict:
    if not isinstance(block, dict):
        raise SignalSpecError(f'{where} must be a mapping, got {block!r}')
    unknown = sorted(set(map(str, block)) - set(required) - set(optional))
    if unknown:
        raise SignalSpecError(f'{where}: unknown field(s) {unknown}; allowed: '
                              f'{", ".join(required + optional)}')
    missing = [k for k in required if k not in block]
    if missing:
        raise SignalSpecError(f'{where}: missing field(s) {missing}')
    return block


def _multisine_axis(block: Any, where: str, limit: float = MAX_TORQUE) -> TorqueFunction:
    block = _fields(block, where, ('amplitudes', 'frequencies'), ('phases', 'offset'))
    amps = _numbers(block['amplitudes'], f'{where}.amplitudes', 0.0, limit)
    freqs = _numbers(block['frequencies'], f'{where}.frequencies', 0.0, MAX_FREQUENCY,
                     open_low=True)
    phases = (_numbers(block['phases'], f'{where}.phases', -1e3, 1e3) if 'phases' in block
              else [0.0] * len(amps))
    if not len(amps) == len(freqs) == len(phases):
        raise SignalSpecError(f'{where}: amplitudes, frequencies and phases must have the same '
                              f'length, got {len(amps)}, {len(freqs)} and {len(phases)}')
    offset = _number(block.get('offset', 0.0), f'{where}.offset', -limit, limit)
    terms = list(zip(amps, freqs, phases))
    return lambda t: offset + sum(a * np.sin(2 * np.pi * f * t + p) for a, f, p in terms)


def _chirp_axis(block: Any, where: str, duration: float,
                limit: float = MAX_TORQUE) -> TorqueFunction:
    block = _fields(block, where, ('amplitude', 'f0', 'f1'), ('phase', 'offset', 'method'))
    amp = _number(block['amplitude'], f'{where}.amplitude', 0.0, limit)
    f0 = _number(block['f0'], f'{where}.f0', 0.0, MAX_FREQUENCY, open_low=True)
    f1 = _number(block['f1'], f'{where}.f1', 0.0, MAX_FREQUENCY, open_low=True)
    phase = _number(block.get('phase', 0.0), f'{where}.phase', -1e3, 1e3)
    offset = _number(block.get('offset', 0.0), f'{where}.offset', -limit, limit)
    method = block.get('method', 'linear')
    if method not in CHIRP_METHODS:
        raise SignalSpecError(f'{where}.method must be one of {list(CHIRP_METHODS)}, '
                              f'got {method!r}')
    if method == 'logarithmic' and f0 != f1:
        k = f1 / f0                # instantaneous frequency f0·k^(t/T): phase is its integral
        scale = 2 * np.pi * f0 * duration / math.log(k)
        return lambda t: offset + amp * np.sin(scale * (np.power(k, t / duration) - 1.0) + phase)
    rate = (f1 - f0) / duration    # linear: f(t) = f0 + rate·t
    return lambda t: offset + amp * np.sin(2 * np.pi * (f0 * t + 0.5 * rate * t * t) + phase)


def _axes(m: int) -> tuple[str, ...]:
    return tuple(f'ax{k}' for k in range(m))


def _signal_from_spec(name: str, block: Any, source: str, m: int = 2,
                      limit: float = MAX_TORQUE) -> Signal:
    where = f'{source}: signals.{name}'
    if not _NAME.fullmatch(name):
        raise SignalSpecError(f'{where}: a signal name is letters, digits and underscores, not '
                              'starting with a digit')
    if name in SIGNALS:
        raise SignalSpecError(f'{where}: {name!r} is a built-in signal; give yours another name')
    axes_names = _axes(m)
    block = _fields(block, where, ('kind', 'duration'), axes_names)
    kind = block['kind']
    if kind not in KINDS:
        raise SignalSpecError(f'{where}.kind must be one of {list(KINDS)}, got {kind!r}')
    duration = _number(block['duration'], f'{where}.duration', 0.0, MAX_DURATION, open_low=True)
    if not any(axis in block for axis in axes_names):
        define = ('ax0, ax1 or both' if m == 2 else 'ax0' if m == 1
                  else f'at least one of {", ".join(axes_names)}')
        raise SignalSpecError(f'{where}: define {define} (an axis left out gets zero torque)')
    axes = []
    for axis in axes_names:
        if axis not in block:
            axes.append(lambda t: np.zeros_like(t))
        elif kind == 'multisine':
            axes.append(_multisine_axis(block[axis], f'{where}.{axis}', limit))
        else:
            axes.append(_chirp_axis(block[axis], f'{where}.{axis}', duration, limit))

    def torque(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return np.stack([np.broadcast_to(f(t), t.shape) for f in axes], axis=-1)

    return Signal(name, duration, torque)


def parse_signal_specs(doc: Any, source: str = '<spec>', m: int = 2,
                       limit: float = MAX_TORQUE) -> dict[str, Signal]:
    """The signals of a parsed YAML document ``{signals: {name: {...}}}`` (module doc), for
    ``m`` inputs, amplitudes and offsets up to ``limit``.

    Raises:
        SignalSpecError: the first problem, naming ``source`` and the field.
    """
    if not isinstance(doc, dict) or set(doc) != {'signals'}:
        raise SignalSpecError(f'{source}: must hold one mapping "signals:" of name → signal, got '
                              f'{sorted(doc) if isinstance(doc, dict) else type(doc).__name__}')
    specs = doc['signals']
    if not isinstance(specs, dict) or not specs:
        raise SignalSpecError(f'{source}: "signals" must map at least one name to a signal')
    return {str(name): _signal_from_spec(str(name), block, source, m, limit)
            for name, block in specs.items()}


def load_signal_specs(path: str | Path, m: int = 2,
                      limit: float = MAX_TORQUE) -> dict[str, Signal]:
    """The user-defined signals in the YAML file ``path`` for ``m`` inputs (amplitudes and
    offsets up to ``limit``).

    Raises:
        SignalSpecError: missing or unreadable file, invalid YAML, or a bad field (named).
    """
    path = Path(path)
    if not path.is_file():
        raise SignalSpecError(f'signal file {path} does not exist' if not path.exists()
                              else f'signal file {path} is not a file')
    try:
        doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    except (OSError, UnicodeDecodeError) as exc:
        raise SignalSpecError(f'signal file {path} cannot be read: {exc}') from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        at = f' (line {mark.line + 1}, column {mark.column + 1})' if mark is not None else ''
        raise SignalSpecError(f'signal file {path} is not valid YAML{at}: '
                              f'{getattr(exc, "problem", exc)}') from None
    return parse_signal_specs(doc, str(path), m, limit)


def resolve_signals(names: Sequence[str], spec_file: str | Path | None = None,
                    duration: float | None = None, m: int | None = None,
                    limit: float = MAX_TORQUE, one_sided: bool = False) -> list[Signal]:
    """The signals called ``names``: built-in, or defined in ``spec_file``; ``duration`` (if given)
    replaces each one's own length. Without ``m`` the hand's two torques; with ``m`` the
    signals of m inputs (module doc), a spec file's amplitudes and offsets up to ``limit``;
    ``one_sided``: every input only pushes or only pulls (:func:`builtin_signal`).

    Raises:
        SignalSpecError: no names, a bad spec file, or a name found in neither place.
    """
    if not names:
        raise SignalSpecError('name at least one signal')
    user = load_signal_specs(spec_file, 2 if m is None else m, limit) if spec_file else {}
    out = []
    for name in names:
        if name in user:
            signal = user[name]
        elif name in SIGNALS:
            signal = builtin_signal(name, m=m, one_sided=one_sided)
        else:
            known = list(SIGNALS) + list(user)
            raise SignalSpecError(f'unknown signal {name!r}; known: {", ".join(known)}'
                                  + ('' if spec_file
                                     else ' (user-defined signals need a spec file)'))
        if duration is not None:
            signal = Signal(signal.name, float(duration), signal.torque, signal.share)
        out.append(signal)
    return out
