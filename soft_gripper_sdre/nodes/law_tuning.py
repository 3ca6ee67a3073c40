"""The controller node's law as its parameters build it, and the rules for retuning it while the
node runs (no ROS: the node holds a :class:`LawTuning` and reports what it returns).

The parameters are the node's (``law``, ``q_pos``, ``integral_gain``, ``pd_kp``, …); each law
reads only those its file declares (:class:`~soft_gripper_sdre.control.laws.registry.LawParam`,
the :data:`~soft_gripper_sdre.control.laws.LAW_REGISTRY` entry's ``params``), and the registry
maps them to the law's options (:func:`~soft_gripper_sdre.control.laws.registry.node_options`).
The runtime parameters are those the law files declare ``runtime``. A runtime
change is checked by building the law with the new values, so a refused one leaves the old law
and values in force; an accepted one replaces the law after
:func:`~soft_gripper_sdre.control.laws.hand_over` gave the new law the state that keeps the
command continuous (the roll-off's last output, the integral's torque). A change to a value the
law does not read is taken and has no effect.
"""
from __future__ import annotations

from soft_gripper_sdre.control.laws import LAW_REGISTRY, hand_over, make_law
from soft_gripper_sdre.control.laws.registry import law_params, node_options, shown_values
from soft_gripper_sdre.control.tracking import Law, Weights

#: the parameters that may be changed while the node runs and retune the law (the law files'
#: runtime parameters)
TUNABLE = tuple(p.name for p in law_params() if p.runtime)
#: every node parameter the law is built from
LAW_PARAMS = ('law', 'solver', 'torque_limit', 'torque_lowpass_hz', 'control_period',
              *(p.name for p in law_params()))


class LawTuning:
    """The law in force, built from the node's parameters, and its runtime retuning.

    Args:
        model: the learned SDC model every law is built on.
        n_fingers: the fingers controlled together.
        params: the node's parameters (at least :data:`LAW_PARAMS`).
        bounds: the bounds of each of the model's inputs; None = ±``torque_limit`` on each.

    Raises:
        ValueError: a value the law refuses (the message names it).
    """

    def __init__(self, model, n_fingers: int, params: dict, bounds=None) -> None:
        self.model = model
        self.n = n_fingers
        self.bounds = bounds
        self.params = {name: params[name] for name in LAW_PARAMS}
        self.law: Law = self.build(self.params)
        self._retuned: Law | None = None    # the law built by an accepted runtime change

    @property
    def name(self) -> str:
        return self.params['law']

    def build(self, p: dict) -> Law:
        """The control law of the parameters ``p``.

        Raises:
            ValueError: a value the law refuses (the message names it).
        """
        return make_law(p['law'], self.model, Weights(p['q_pos'], p['q_vel'], p['r']),
                        p['torque_limit'], n_fingers=self.n, method=p['solver'],
                        lowpass_hz=p['torque_lowpass_hz'], dt=p['control_period'],
                        bounds=self.bounds, **node_options(p['law'], p))

    def uses(self, name: str) -> bool:
        """Whether the law in use reads the parameter ``name`` (its file declares it)."""
        return any(p.name == name for p in LAW_REGISTRY[self.name].params)

    def check(self, new: dict) -> str | None:
        """Why the runtime change ``new`` (parameter name → value) is refused, or None; an
        accepted change to a value the law uses builds the law it will run (:meth:`apply` puts
        it in force)."""
        self._retuned = None
        if not any(self.uses(name) for name in TUNABLE if name in new):
            return None
        try:
            self._retuned = self.build({**self.params, **new})
        except ValueError as exc:
            return f'{", ".join(sorted(new))}: {exc}'
        return None

    def apply(self, new: dict) -> str | None:
        """Put the change ``new`` that :meth:`check` accepted in force; what it did, for the log
        (None: it changed no tunable value)."""
        tuned = {name: new[name] for name in TUNABLE if name in new}
        if not tuned:
            return None
        self.params.update(tuned)
        changes = ', '.join(f'{name} = {value:g}' for name, value in tuned.items())
        if self._retuned is None:
            return f'{changes}: not used by the {self.name} law, no effect'
        hand_over(self.law, self._retuned)
        self.law, self._retuned = self._retuned, None
        return f'{changes}: the {self.name} law is retuned from the next estimate'

    def shown(self) -> dict[str, str]:
        """The tunable values in force, as /diagnostics shows them (``weights``,
        ``integral``, ``pd_gains``, …: :func:`~soft_gripper_sdre.control.laws.registry.
        shown_values`)."""
        return shown_values(self.name, self.params)
