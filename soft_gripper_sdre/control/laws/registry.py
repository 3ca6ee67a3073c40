"""The law registry: every law file registers its builder and declares its own parameters.

A law file ends with :func:`register_law` (name, builder, the ``make_law`` options it takes, its
node parameters as :class:`LawParam`, whether it runs on the node graph, a one-line summary), so
the registry is filled by importing the law files (the package's ``__init__`` imports them in the
order the registry lists them). Everything that presents a law's parameters is derived from it:
the controller node's ``PARAMS`` (:func:`law_params`, :func:`node_description`), the runtime
retuning of :class:`~soft_gripper_sdre.nodes.law_tuning.LawTuning` (:func:`node_options`,
:func:`shown_values`), ``controller --help``, docs/parameters.md and config/controller.yaml
(rendered from ``PARAMS``, checked by tests). Parameters several laws read (the SDRE weights
:data:`WEIGHT_PARAMS`; the task-space PD gains of ``pd`` and ``computed_torque``) are declared
once and listed by each law that reads them.

No ROS here: the node turns a :class:`LawParam` into its parameter declaration.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Callable, Mapping, NamedTuple

from soft_gripper_sdre.control.tracking import (
    DEFAULT_LOWPASS_HZ,
    DEFAULT_WEIGHTS,
    Law,
    Weights,
    law_bounds,
    shape_of,
)
from soft_gripper_sdre.sim.shape import HAND_SHAPE, InputBounds

__all__ = ['LAW_REGISTRY', 'LawEntry', 'LawParam', 'LawSettings', 'OPTION_MEANINGS',
           'WEIGHT_PARAMS', 'graph_laws', 'law_params', 'make_law', 'model_shape',
           'node_description', 'node_options', 'readers', 'register_law', 'shown_values']


@dataclass(frozen=True)
class LawParam:
    """One node parameter a law reads: what the controller declares and what it feeds.

    ``name``, ``default`` (its type is the parameter's), ``description``, ``units`` (SI),
    ``min``/``max`` (the accepted range, inclusive) or ``choices`` are the node parameter's
    declaration; ``runtime``: it may be changed while the node runs (the law is then rebuilt and
    handed over), else read-only.

    ``option``: the :func:`make_law` option the value feeds ('' = a setting every law is built
    from: the SDRE weights, :data:`WEIGHT_PARAMS`); with ``key`` the option is a dict and the
    value is its entry ``key`` (``pd_kp`` → ``pd_gains['kp']``). ``zero_is_own``: 0 stands for
    the reading law's own value (:attr:`LawEntry.own`). ``strict``: a value other than the
    default is refused when the law in use does not read the parameter (a switch that asks for
    something only some laws do, e.g. the state-dependent Q(x)); any other parameter a law does
    not read is taken and has no effect. ``shown``: (key, label) of a runtime parameter in the
    controller's /diagnostics values (``weights: q_pos=… q_vel=… r=…``).
    """

    name: str
    default: Any
    description: str
    units: str = ''
    min: float | None = None
    max: float | None = None
    choices: tuple | None = None
    runtime: bool = False
    option: str = ''
    key: str = ''
    zero_is_own: bool = False
    strict: bool = False
    shown: tuple[str, str] | None = None

    def refusal(self, value: Any) -> str | None:
        """Why ``value`` is outside this parameter's declaration, or None (the node's check;
        here for callers without ROS)."""
        if self.choices is not None and value not in self.choices:
            return f'{self.name} must be one of {list(self.choices)}, got {value!r}'
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                return f'{self.name} must be finite, got {value!r}'
            if self.min is not None and value < self.min:
                return f'{self.name} must be >= {self.min}, got {value!r}'
            if self.max is not None and value > self.max:
                return f'{self.name} must be <= {self.max}, got {value!r}'
        return None


#: the SDRE weights Q = diag(q_pos I_d, q_vel I_d), R = r I_m (SI): the ``weights`` every law is
#: built with, read by the laws that list them
WEIGHT_PARAMS = (
    LawParam('q_pos', DEFAULT_WEIGHTS['q_pos'], 'SDRE state weight on tip position, Q = '
             'diag(q_pos I_d, q_vel I_d), d the tip\'s coordinates (paper: 2 in sim units = 800 '
             'SI)', '1/m²', 0.0,
             1e12, runtime=True, shown=('weights', 'q_pos')),
    LawParam('q_vel', DEFAULT_WEIGHTS['q_vel'], 'SDRE state weight on tip velocity', 's²/m²',
             0.0, 1e12, runtime=True, shown=('weights', 'q_vel')),
    LawParam('r', DEFAULT_WEIGHTS['r'], 'SDRE input weight, R = r I_m, m the inputs (paper: 0.1 '
             'in sim units = 16000 SI)', '1/(input unit)²', 1e-12, 1e12, runtime=True,
             shown=('weights', 'r')),
)


@dataclass(frozen=True)
class LawSettings:
    """What every law is built from (:func:`make_law`'s shared arguments)."""

    model: object                 # the learned SDC model (AG, rest_tip, optionally sdc_blocks)
    weights: Weights
    u_max: float                  # torque saturation [N·m] where bounds is None
    n_fingers: int = 4
    method: str = 'fast'          # the SDRE solver: 'fast' or 'reference'
    lowpass_hz: float = DEFAULT_LOWPASS_HZ
    dt: float = 1e-3              # control period [s]
    bounds: InputBounds | None = None   # per-input [lower, upper]; None: ±u_max on each input


class LawEntry(NamedTuple):
    """A registered law: ``build(settings, **options)``, the names of the options it takes, the
    node parameters it reads, whether the controller node runs it (``graph``), a one-line
    ``summary`` for the ``law`` parameter's help, and ``own``: its own value of each
    ``zero_is_own`` parameter (parameter name → value)."""

    build: Callable[..., Law]
    options: tuple[str, ...] = ()
    params: tuple[LawParam, ...] = ()
    graph: bool = False
    summary: str = ''
    own: Mapping[str, float] | None = None


#: law name → how to build it; the law files fill it through :func:`register_law`
LAW_REGISTRY: dict[str, LawEntry] = {}
#: option name → what it means (for the refusal of an option a law does not take)
OPTION_MEANINGS: dict[str, str] = {}


def register_law(name: str, build: Callable[..., Law], options: tuple[str, ...] = (), *,
                 params: tuple[LawParam, ...] = (), graph: bool = False, summary: str = '',
                 own: Mapping[str, float] | None = None,
                 meanings: Mapping[str, str] | None = None) -> None:
    """Make ``make_law(name, …)`` build ``build(settings, **options)`` (replacing an earlier
    entry). ``options``: the options it takes besides those its ``params`` feed; ``params``: the
    node parameters it reads (:class:`LawParam`); ``graph``: the controller node runs it;
    ``summary``: one line for the ``law`` parameter's help; ``own``: its value of each
    ``zero_is_own`` parameter; ``meanings``: option name → meaning, for error messages.

    Raises:
        ValueError: a ``zero_is_own`` parameter without the law's own value, or a parameter whose
            default is outside its own range or choices.
    """
    for p in params:
        if p.zero_is_own and (own is None or p.name not in own):
            raise ValueError(f'law {name!r}: parameter {p.name!r} takes 0 as the law\'s own '
                             'value; give it in own')
        why = p.refusal(p.default)
        if why:
            raise ValueError(f'law {name!r}: the default of parameter {p.name!r}: {why}')
    fed = [p.option for p in params if p.option]
    LAW_REGISTRY[name] = LawEntry(build, tuple(dict.fromkeys([*options, *fed])), tuple(params),
                                  graph, summary, dict(own) if own else None)
    OPTION_MEANINGS.update(meanings or {})


def graph_laws() -> tuple[str, ...]:
    """The registered laws the controller node runs, in registry order."""
    return tuple(name for name, entry in LAW_REGISTRY.items() if entry.graph)


def law_params(laws: tuple[str, ...] | None = None) -> tuple[LawParam, ...]:
    """Every node parameter the ``laws`` (default: :func:`graph_laws`) read, each once, in
    registry order.

    Raises:
        ValueError: two laws declare different parameters of one name.
    """
    seen: dict[str, LawParam] = {}
    for law in graph_laws() if laws is None else laws:
        for p in LAW_REGISTRY[law].params:
            if seen.setdefault(p.name, p) != p:
                raise ValueError(f'laws declare parameter {p.name!r} twice, differently; declare '
                                 'it once and list it in each law')
    return tuple(seen.values())


def readers(name: str, laws: tuple[str, ...] | None = None) -> tuple[str, ...]:
    """The ``laws`` (default: :func:`graph_laws`) that read the node parameter ``name``."""
    return tuple(law for law in (graph_laws() if laws is None else laws)
                 if any(p.name == name for p in LAW_REGISTRY[law].params))


def _listed(names) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else f'{", ".join(names[:-1])} and {names[-1]}'


def node_description(param: LawParam, laws: tuple[str, ...] | None = None) -> str:
    """The controller's description of ``param``: which of the ``laws`` (default:
    :func:`graph_laws`) read it when not all do (``pd and computed_torque only: …``, or ``…;
    every law but pd`` when most do), and each reader's own value of a ``zero_is_own`` parameter
    (``(15000 for pd, …)``)."""
    laws = graph_laws() if laws is None else laws
    users = readers(param.name, laws)
    text = param.description
    if param.zero_is_own:
        text += ' (' + ', '.join(f'{LAW_REGISTRY[law].own[param.name]:g} for {law}'
                                 for law in users) + ')'
    others = [law for law in laws if law not in users]
    if not others:
        return text
    if len(others) < len(users):
        return f'{text}; every law but {_listed(others)}'
    return f'{_listed(users)} only: {text}'


def _in_force(param: LawParam, law: str, value: Any) -> Any:
    """``value`` of ``param`` as ``law`` takes it: 0 of a ``zero_is_own`` parameter is the law's
    own value (for a law that does not read it, that of the first law that does)."""
    if not param.zero_is_own or value:
        return value
    owner = law if param in LAW_REGISTRY[law].params else readers(param.name,
                                                                  tuple(LAW_REGISTRY))[0]
    return LAW_REGISTRY[owner].own[param.name]


def node_options(law: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """The :func:`make_law` options of ``law`` from the node's parameter ``values`` (name →
    value; at least those of :func:`law_params`): each parameter the law reads to its option.

    Raises:
        ValueError: unknown law, or a ``strict`` parameter the law does not read set other than
            its default (the message names the parameter, its meaning and the laws that read it).
    """
    entry = LAW_REGISTRY.get(law)
    if entry is None:
        raise ValueError(f'unknown law {law!r}; known: {tuple(LAW_REGISTRY)}')
    options: dict[str, Any] = {}
    for p in entry.params:
        if not p.option:
            continue
        value = _in_force(p, law, values[p.name])
        if p.key:
            options.setdefault(p.option, {})[p.key] = value
        else:
            options[p.option] = value
    for p in law_params():
        if p.strict and p not in entry.params and values[p.name] != p.default:
            meaning = f' ({OPTION_MEANINGS[p.option]})' if p.option in OPTION_MEANINGS else ''
            raise ValueError(f'{p.name}={values[p.name]!r}{meaning} is not read by the {law!r} '
                             f'law; laws that read it: {list(readers(p.name))}')
    return options


def shown_values(law: str, values: Mapping[str, Any]) -> dict[str, str]:
    """The runtime parameters' values in force under ``law``, grouped as the controller's
    /diagnostics shows them (``{'weights': 'q_pos=1e+06 q_vel=0 r=16000', …}``; 0 of a
    ``zero_is_own`` parameter shown as the value it stands for)."""
    groups: dict[str, list[str]] = {}
    for p in law_params():
        if p.runtime and p.shown is not None:
            key, label = p.shown
            groups.setdefault(key, []).append(f'{label}={_in_force(p, law, values[p.name]):g}')
    return {key: ' '.join(items) for key, items in groups.items()}


def model_shape(model):
    """The model's shape; no model (the Koopman laws need none) is the hand's."""
    return HAND_SHAPE if model is None else shape_of(model)


def make_law(name: str, model, weights: Weights, u_max: float, n_fingers: int = 4,
             method: str = 'fast', lowpass_hz: float = DEFAULT_LOWPASS_HZ, dt: float = 1e-3,
             bounds: InputBounds | None = None, **options) -> Law:
    """The law registered as ``name`` with the shared settings and its own ``options``.

    ``bounds``: per-input [lower, upper] the law clips to, one per input of the model (None: ±u_max
    on each). An option the law does not take is refused unless it is off (None or False), so
    callers can pass e.g. ``adaptive=False`` to any law.

    Raises:
        ValueError: unknown law, or an option the law does not take, or a bad setting
            (:class:`~soft_gripper_sdre.sim.shape.ShapeError`, a ValueError, for a model whose
            shape cannot be told, bounds of another number of inputs, or a shape the law does
            not take).
    """
    entry = LAW_REGISTRY.get(name)
    if entry is None:
        raise ValueError(f'unknown law {name!r}; known: {tuple(LAW_REGISTRY)} (the oracle laws '
                         'are known after analysis.oracle.register_oracle_laws())')
    taken = {}
    for key, value in options.items():
        if key in entry.options:
            taken[key] = value
        elif value is not None and value is not False:
            owners = [n for n, e in LAW_REGISTRY.items() if key in e.options]
            meaning = f' ({OPTION_MEANINGS[key]})' if key in OPTION_MEANINGS else ''
            raise ValueError(f'{key}={value!r}{meaning} is not an option of the {name!r} law; '
                             f'laws that take it: {owners or "none"}')
    if bounds is not None:
        law_bounds(model_shape(model), u_max, bounds)      # the bounds fit the model's inputs
    return entry.build(LawSettings(model, weights, u_max, n_fingers, method, lowpass_hz, dt,
                                   bounds), **taken)
