"""The law registry (control/laws/registry.py): each law file declares its node parameters and
registers itself, and the controller's PARAMS, its --help, LawTuning's tunables and option
mapping, docs/parameters.md, config/controller.yaml and the launch file's help follow from it; a
law registered by a test shows up in each without an edit elsewhere; bad declarations are
refused by name."""
from pathlib import Path
import re

import numpy as np
import pytest
from sdc_models import StiffeningModel
import yaml

from soft_gripper_sdre.control.laws import (
    DEFAULT_CT,
    DEFAULT_PD,
    GRAPH_LAWS,
    LAW_REGISTRY,
    LawParam,
    make_law,
    register_law,
)
from soft_gripper_sdre.control.laws.registry import (
    OPTION_MEANINGS,
    graph_laws,
    law_params,
    node_description,
    node_options,
    readers,
    shown_values,
)
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, LawIO, Weights

ROOT = Path(__file__).resolve().parents[1]
W = Weights(**DEFAULT_WEIGHTS)


def controller_params():
    from soft_gripper_sdre.nodes.controller import PARAMS
    return {p.name: p for p in PARAMS}


def node_values(**changes):
    """The controller's default parameter values with ``changes``."""
    return {**{name: p.default for name, p in controller_params().items()}, **changes}


# -- what the node, its docs and its config take from the registry -----------------------------
def test_the_controllers_law_parameters_are_the_law_files_declarations():
    declared = controller_params()
    for p in law_params():
        q = declared[p.name]
        assert (q.default, q.units, q.min, q.max, q.choices, q.read_only) == (
            p.default, p.units, p.min, p.max, p.choices, not p.runtime), p.name
        assert q.description == node_description(p)
    law = declared['law']
    assert law.choices == GRAPH_LAWS == graph_laws()
    assert all(f'{name}: {LAW_REGISTRY[name].summary}' in law.description for name in GRAPH_LAWS)
    # every parameter a law reads is declared once, in the order the laws declare them
    names = list(declared)
    assert [n for n in names if n in {p.name for p in law_params()}] == [
        p.name for p in law_params() if not p.option] + [p.name for p in law_params() if p.option]


def _doc_rows():
    text = (ROOT / 'docs' / 'parameters.md').read_text(encoding='utf-8')
    section = text[text.index('## controller'):text.index('## recorder')]
    rows = re.findall(r'^\| `(\w+)` \| (.*?) \| (.*?) \| (.*?) \| (.*?) \| .* \|$', section,
                      re.MULTILINE)
    return {name: cells for name, *cells in rows}


def _limits(p: LawParam) -> str:
    if p.choices:
        return ', '.join(f'`{c}`' for c in p.choices)
    return '' if p.min is None else f'[{p.min:g}, {p.max:g}]'


def test_the_parameter_reference_rows_agree_with_the_registry():
    """docs/parameters.md's controller table: name, default, units, range and runtime of each law
    parameter as its law file declares them."""
    rows = _doc_rows()
    for p in law_params():
        default, units, limits, runtime = rows[p.name]
        assert default == f'`{p.default!r}`', p.name
        assert units == p.units and limits.replace('\\|', '|') == _limits(p), p.name
        assert runtime == ('yes' if p.runtime else ''), p.name
    assert rows['law'][2] == ', '.join(f'`{name}`' for name in GRAPH_LAWS)


def test_the_shipped_config_holds_each_law_parameters_default():
    doc = yaml.safe_load((ROOT / 'config' / 'controller.yaml').read_text())
    values = doc['/**/controller']['ros__parameters']
    for p in law_params():
        assert values[p.name] == p.default and type(values[p.name]) is type(p.default), p.name


def test_help_lists_each_law_parameter_with_its_units_and_range(capsys):
    from soft_gripper_sdre.nodes.controller import main
    assert main(['controller', '--help']) == 0
    text = capsys.readouterr().out
    for p in law_params():
        line = f'  {p.name} = {p.default!r}' + (f'; {p.units}' if p.units else '')
        assert line in text, line
        limits = _limits(p).replace('`', '')
        assert (f'[{p.min:g}, {p.max:g}]' if p.min is not None
                else f'one of {limits}' if p.choices else '') in text
    assert 'one of ' + ', '.join(GRAPH_LAWS) in text


def test_the_launch_files_law_argument_lists_every_graph_law(launch_module):
    module = launch_module
    text = next(text for name, _, text in module.ARGUMENTS if name == 'law')
    assert module.argument_help('law', text).endswith(f': {", ".join(GRAPH_LAWS)}')
    assert module.argument_help('noise', 'σ') == 'σ'
    with pytest.raises(ValueError, match='smc'):             # the refusal lists them too
        module.grasp_nodes(law='smcc')


def test_law_tuning_tunes_what_the_law_files_declare_runtime_and_reads_only_a_laws_own():
    from soft_gripper_sdre.learning.model import SDCModel
    from soft_gripper_sdre.nodes.law_tuning import LAW_PARAMS, TUNABLE, LawTuning
    assert TUNABLE == tuple(p.name for p in law_params() if p.runtime)
    assert set(LAW_PARAMS) >= {p.name for p in law_params()}
    model = SDCModel()
    for law in GRAPH_LAWS:
        t = LawTuning(model, 4, node_values(law=law))
        own = {p.name for p in LAW_REGISTRY[law].params}
        assert {name for name in TUNABLE if t.uses(name)} == own & set(TUNABLE), law
        assert set(t.shown()) == {p.shown[0] for p in law_params() if p.shown}


# -- the registry's rules ----------------------------------------------------------------------
def test_parameters_map_to_the_laws_options_and_zero_stands_for_the_laws_own():
    values = node_values(pd_kd=5.0, integral_gain=0.0, feedforward_at='ref')
    assert node_options('pd', values) == {'pd_gains': dict(kp=DEFAULT_PD['kp'], kd=5.0)}
    assert node_options('computed_torque', node_values()) == {'pd_gains': DEFAULT_CT}
    assert node_options('sdre_ff', values) == dict(ff_at='ref', integral_gain=0.0,
                                                   integral_band=values['integral_band'])
    assert node_options('sdre', node_values(state_weights=True)) == {'adaptive': True}
    assert node_options('lqr', node_values(feedforward_at='ref')) == {}   # not its: no effect
    assert shown_values('computed_torque', node_values())['pd_gains'] == (
        f'kp={DEFAULT_CT["kp"]:g} kd={DEFAULT_CT["kd"]:g}')
    assert readers('pd_kp') == ('pd', 'computed_torque')


@pytest.mark.parametrize('law', ['pd', 'lqr', 'smc', 'sdre_ff'])
def test_a_strict_switch_a_law_does_not_read_is_refused_naming_the_parameter(law):
    with pytest.raises(ValueError, match=rf"state_weights=True \(state-dependent weights Q\(x\)\) "
                                         rf"is not read by the '{law}' law; laws that read it: "
                                         rf"\['sdre'\]"):
        node_options(law, node_values(state_weights=True))
    with pytest.raises(ValueError, match='unknown law'):
        node_options('smcc', node_values())


def test_the_declared_range_refuses_bad_values_by_name():
    p = next(q for q in law_params() if q.name == 'smc_phi')
    assert p.refusal(p.default) is None
    for bad, why in ((0.0, '>= 1e-06'), (1e3, '<= 100'), (float('nan'), 'finite'),
                     (float('inf'), 'finite')):
        assert p.refusal(bad).startswith('smc_phi must be') and why in p.refusal(bad)
    ff = next(q for q in law_params() if q.name == 'feedforward_at')
    assert "feedforward_at must be one of ['x', 'ref']" in ff.refusal('model')


class ToyLaw:
    """u = −gain (p − p_d) through nothing: a law of one parameter for the registry tests."""

    def __init__(self, model, u_max, gain, n_fingers):
        self.io = LawIO(model.rest_tip, u_max, n_fingers, 0.0, 1e-3)
        self.gain = gain

    def reset(self):
        self.io.reset()

    def compute(self, pos, vel, ref_pos, ref_vel, ref_acc=None):
        x, xd, finite = self.io.states(pos, vel, ref_pos, ref_vel)
        return self.io.finish(-self.gain * (x - xd)[:, :2], finite)


TOY_GAIN = LawParam('toy_gain', 2.0, 'the toy law\'s gain', 'N·m/m', 0.0, 10.0, runtime=True,
                    option='toy_gain', shown=('toy', 'gain'))


@pytest.fixture
def toy(monkeypatch):
    """The toy law registered as one law file would, removed again after the test."""
    monkeypatch.setitem(LAW_REGISTRY, 'toy', None)
    monkeypatch.setitem(OPTION_MEANINGS, 'toy_gain', None)
    register_law('toy', lambda s, toy_gain=2.0: ToyLaw(s.model, s.u_max, toy_gain, s.n_fingers),
                 params=(TOY_GAIN,), graph=True, summary='a toy',
                 meanings={'toy_gain': 'the toy gain'})
    return 'toy'


def test_a_law_registered_as_a_file_would_is_wired_through_the_registry(toy):
    assert toy in graph_laws() and law_params()[-1] == TOY_GAIN
    assert node_description(TOY_GAIN) == "toy only: the toy law's gain"
    values = {**node_values(), 'toy_gain': 3.0}
    assert node_options(toy, values) == {'toy_gain': 3.0}
    assert shown_values(toy, values)['toy'] == 'gain=3'
    law = make_law(toy, StiffeningModel(), W, 0.05, n_fingers=1, **node_options(toy, values))
    p = StiffeningModel.rest_tip[None, :2]
    np.testing.assert_allclose(law.compute(p + 0.001, 0 * p, p, 0 * p).u, [[-0.003, -0.003]])
    with pytest.raises(ValueError, match=r"toy_gain=3.0 \(the toy gain\) is not an option of the "
                                         r"'pd' law; laws that take it: \['toy'\]"):
        make_law('pd', StiffeningModel(), W, 0.05, toy_gain=3.0)


@pytest.mark.parametrize('params, own, match', [
    ((LawParam('x_gain', 0.0, 'g', zero_is_own=True, option='x'),), None,
     "parameter 'x_gain' takes 0 as the law's own value; give it in own"),
    ((LawParam('x_gain', 20.0, 'g', min=0.0, max=10.0, option='x'),), None,
     "the default of parameter 'x_gain': x_gain must be <= 10.0, got 20.0"),
    ((LawParam('x_mode', 'c', 'g', choices=('a', 'b'), option='x'),), None,
     "x_mode must be one of \\['a', 'b'\\], got 'c'"),
])
def test_bad_declarations_are_refused_naming_the_law_and_parameter(monkeypatch, params, own,
                                                                     match):
    monkeypatch.setitem(LAW_REGISTRY, 'bad', None)
    with pytest.raises(ValueError, match=rf"law 'bad': .*{match}"):
        register_law('bad', lambda s: None, params=params, own=own)


def test_one_parameter_declared_twice_differently_is_refused(toy):
    other = LawParam('toy_gain', 5.0, 'another gain', option='toy_gain')
    register_law(toy, LAW_REGISTRY[toy].build, params=(other,), graph=True)
    LAW_REGISTRY['toy_too'] = LAW_REGISTRY[toy]._replace(params=(TOY_GAIN,))
    try:
        with pytest.raises(ValueError, match="parameter 'toy_gain' twice, differently"):
            law_params()
    finally:
        del LAW_REGISTRY['toy_too']
