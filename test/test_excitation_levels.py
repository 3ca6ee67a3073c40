"""The level per signal (level auto, level_per signal): each signal probed with its own start
reaches the aimed excursion on a spring–damper finger and on a foreign gripper where one
amplitude for every signal falls short; its bad settings are refused naming them (no ROS)."""
import numpy as np
import pytest
from spring_finger import RATE, SpringDamper

from soft_gripper_sdre.nodes.excitation import PARAMS, excitation_run
from soft_gripper_sdre.nodes.params import ParameterError
from soft_gripper_sdre.sim.excitation import ExcitationPlan
from soft_gripper_sdre.sim.excitation_run import Phase
from soft_gripper_sdre.sim.plants.presets import RATES, make_plant
from soft_gripper_sdre.sim.signal_specs import builtin_signal


def params(**kw) -> dict:
    p = {q.name: q.default for q in PARAMS}
    p.update(finger_names=['a'], finger=-1, input_lower='', input_upper='', torque_limit=0.1,
             settle_time=0.5, settle_samples=0, level='auto', max_excursion=0.016)
    p.update(kw)
    return p


def peaks(run, tips, step, rate: float) -> dict[str, float]:
    """Drive ``run`` to its end; the peak excursion [m] while each signal played."""
    rest = tips().copy()
    run.start(rest)
    out, k = {}, 0
    while True:
        st = run.at(k / rate, tips())
        if st.phase is Phase.OVER:
            return out
        if st.phase is Phase.PLAY:
            seg = run.plan.segment_at(st.t)
            if seg is not None:
                e = float(np.linalg.norm(tips()[0] - rest[0]))
                out[seg.signal.name] = max(out.get(seg.signal.name, 0.0), e)
        step(st.u[0])
        k += 1


def test_each_signal_is_played_at_its_own_level_near_the_goal_on_a_spring_finger():
    finger = SpringDamper(gain=0.1)
    run = excitation_run(params(signals=['u1', 'u4', 'x1'], max_excursion=0.02,
                                level_probe_time=2.0), 1)
    got = peaks(run, finger.tips, finger.step, RATE)
    assert [name for name, _ in run.levels] == ['u1', 'u4', 'x1']
    amplitudes = dict(run.levels)
    assert len(set(amplitudes.values())) == 3                  # one level each
    for name, e in got.items():
        assert 0.75 * 0.01 < e < 1.3 * 0.01, (name, e, amplitudes)


def test_on_the_tendon_gripper_each_signal_reaches_the_goal_where_u1s_level_falls_short():
    plant, rate = make_plant('tendon3_index'), RATES['tendon3']
    tips = lambda: np.r_[plant.tip(), 0.0][None]                # noqa: E731
    step = lambda u: plant.step(u, 1.0 / rate)                  # noqa: E731
    p = params(signals=['u1', 'b1'], torque_limit=0.02, level_probe_time=3.0)
    own = peaks(excitation_run(p, 1), tips, step, rate)
    plant.reset()
    one = peaks(excitation_run(dict(p, level_per='plan'), 1), tips, step, rate)
    for name in ('u1', 'b1'):
        assert 0.85 * 0.008 < own[name] < 1.2 * 0.008, (name, own)
    assert one['b1'] < 0.8 * 0.008                               # one level: b1 falls short


def test_the_own_probe_plays_the_signals_start_and_scales_by_its_later_peak():
    plan = ExcitationPlan([builtin_signal('u1'), builtin_signal('u2')], 0.5, 1,
                          torque_limit=0.05)
    second = plan.signal_plan(1)
    assert [s.signal.name for s in second.segments] == ['u2'] and second.duration == 10.5
    probe = second.own_probe(0.5)       # u2 = 25 sin(0.5πt) + 2: 27 at t = 1 s, after the probe
    assert probe.correction == pytest.approx(27 / (25 * np.sin(0.25 * np.pi) + 2), rel=3e-3)
    assert probe.largest == pytest.approx(0.05 / 0.0675, rel=1e-3)
    torque = second.segments[0].signal.torque
    np.testing.assert_allclose(probe.inputs(0.3, 0.5), 0.5 * torque(np.array([0.3]))[0])
    np.testing.assert_array_equal(probe.inputs(0.3, 100.0), [0.05, 0.05])     # the plan's clip
    assert plan.signal_plan(0).own_probe(2.0).correction == pytest.approx(1.0)


@pytest.mark.parametrize('bad, message', [
    (dict(level_per='each'), None),
    (dict(max_excursion=0.0), "parameter 'max_excursion': level auto needs max_excursion > 0"),
    (dict(amplitude=0.5), "parameter 'amplitude'"),
    (dict(signals=['z'], spec_file='SPEC'), "parameter 'signals': signal 'z' is zero over its "
                                            'first 2 s'),
])
def test_bad_level_settings_are_refused_naming_them(bad, message, tmp_path):
    if bad.get('spec_file') == 'SPEC':
        spec = tmp_path / 's.yaml'
        spec.write_text('signals:\n  z: {kind: multisine, duration: 4.0, ax0: {amplitudes: [0.0], '
                        'frequencies: [1.0]}, ax1: {amplitudes: [0.0], frequencies: [1.0]}}\n')
        bad = dict(bad, spec_file=str(spec))
    if message is None:                        # a choice the node's declaration refuses
        choices = next(q.choices for q in PARAMS if q.name == 'level_per')
        assert bad['level_per'] not in choices and set(choices) == {'signal', 'plan'}
        return
    with pytest.raises(ParameterError, match=message.replace('(', r'\(')):
        excitation_run(params(**{'signals': ['u1'], **bad}), 1)
