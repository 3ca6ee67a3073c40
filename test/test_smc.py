"""The sliding-mode law (control/laws/smc.py, ``law:=smc``): its arithmetic against the closed
form on a state-dependent model, tracking on the hand's shipped model in the in-process grasp and
on fingers of other shapes (test/shaped_models.py), bounds and bad values, and on the controller
node: parameters from its file, torques of the offline law, runtime retuning."""
from node_harness import (
    MS,
    TORQUE_LIMIT,
    commands,
    estimate,
    horizon,
    make_controller,
    send_estimate,
)
import numpy as np
import pytest
from rosutil import overrides, ros_context, spin_until
from sdc_models import REST as HAND_REST
from sdc_models import StiffeningModel
from shaped_models import REST, ShapedModel, input_signal, model_reference, rk4, track

from soft_gripper_sdre.control.laws import (
    GRAPH_LAWS,
    LAW_REGISTRY,
    ComputedTorqueLaw,
    hand_over,
    make_law,
)
from soft_gripper_sdre.control.laws.smc import SMC_DEFAULTS, SMC_PARAMS, SmcLaw
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.sim.shape import InputBounds

W = Weights(**DEFAULT_WEIGHTS)
DT = 1e-3
U_MAX = 0.05
#: the shapes tracked and their bounds (one-sided inputs on the hand's shape, as chambers)
SHAPES = {(2, 1): InputBounds.symmetric(U_MAX, 1),
          (3, 3): InputBounds.symmetric(U_MAX, 3),
          (2, 2): InputBounds([0.0, 0.0], [U_MAX, U_MAX]),
          (3, 2): InputBounds.symmetric(U_MAX, 2),
          (2, 4): InputBounds.symmetric(U_MAX, 4)}
SHAPE_IDS = [f'd{d}m{m}' for d, m in SHAPES]


def random_states(rng, n, d=2, spread=3e-3, error=1e-3):
    """(pos, vel, ref_pos, ref_vel, ref_acc) of n fingers about the rest tip: positions
    ``spread`` [m] from it, references ``error`` [m] from them."""
    pos = HAND_REST[:d] + rng.normal(0, spread, (n, d))
    return (pos, rng.normal(0, 0.05, (n, d)), pos + rng.normal(0, error, (n, d)),
            rng.normal(0, 0.05, (n, d)), rng.normal(0, 1.0, (n, d)))


# -- the law's arithmetic ----------------------------------------------------------------------
def test_the_models_tip_acceleration_is_the_sliding_mode_demand():
    """Unsaturated: A₂(x)x + G₂(x)u = a_d − λė − k sat((ė + λe)/φ) exactly, at random states of
    a state-dependent model, with states inside and outside the boundary layer."""
    model, lam, k, phi = StiffeningModel(), 50.0, 3.0, 0.02
    law = SmcLaw(model, 1e9, lam=lam, k=k, phi=phi, n_fingers=5, lowpass_hz=0.0)
    inside = outside = 0
    for seed in range(20):
        pos, vel, ref, ref_vel, ref_acc = random_states(np.random.default_rng(seed), 5,
                                                        error=10 ** (-2 - seed % 3))
        vel = ref_vel + 10 ** (-1 - seed % 3) * (vel - ref_vel)
        out = law.compute(pos, vel, ref, ref_vel, ref_acc=ref_acc)
        x = np.concatenate([pos - HAND_REST[:2], vel], 1)
        A, G = model.AG(x)
        acc = np.einsum('nij,nj->ni', A[:, 2:], x) + np.einsum('nij,nj->ni', G[:, 2:], out.u)
        e, e_dot = pos - ref, vel - ref_vel
        s = e_dot + lam * e
        want = ref_acc - lam * e_dot - k * np.clip(s / phi, -1.0, 1.0)
        np.testing.assert_allclose(acc, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
        np.testing.assert_allclose(law.surface, s, rtol=1e-12)
        inside += int((np.abs(s) < phi).all(axis=1).sum())
        outside += int((np.abs(s) > phi).any(axis=1).sum())
        assert out.ok.all() and not out.fallback.any() and not out.saturated.any()
    assert inside and outside                       # both regimes were exercised


def test_inside_the_boundary_layer_it_is_computed_torque_with_the_layers_pd_gains():
    """|s| < φ: u = G₂⁻¹(a_d − A₂x − (λk/φ) e − (λ + k/φ) ė), computed torque's law."""
    model = StiffeningModel()
    lam, k, phi = 80.0, 4.0, 0.05
    smc = SmcLaw(model, 1e9, lam=lam, k=k, phi=phi, n_fingers=3, lowpass_hz=0.0)
    ct = ComputedTorqueLaw(model, 1e9, kp=lam * k / phi, kd=lam + k / phi, n_fingers=3,
                           lowpass_hz=0.0)
    rng = np.random.default_rng(1)
    for _ in range(10):
        pos, vel, ref, ref_vel, acc = random_states(rng, 3, error=1e-5)
        vel = ref_vel + rng.normal(0, 1e-3, (3, 2))           # |s| ≲ 0.005 m/s < φ
        a, b = (smc.compute(pos, vel, ref, ref_vel, acc), ct.compute(pos, vel, ref, ref_vel, acc))
        assert (np.abs(smc.surface) < phi).all()
        np.testing.assert_allclose(a.u, b.u, rtol=1e-9, atol=1e-15)


def test_the_compiled_path_gives_the_reference_paths_torques_on_the_shipped_model(hand_model):
    fast = make_law('smc', hand_model, W, TORQUE_LIMIT, lowpass_hz=0.0)
    reference = make_law('smc', hand_model, W, TORQUE_LIMIT, lowpass_hz=0.0, method='reference')
    assert fast.network is not None and reference.network is None
    rng = np.random.default_rng(7)
    for _ in range(5):
        pos = hand_model.rest_tip[:2] + rng.normal(0, 5e-3, (4, 2))
        vel, ref_vel, acc = (rng.normal(0, 0.05, (4, 2)), rng.normal(0, 0.05, (4, 2)),
                             rng.normal(0, 1, (4, 2)))
        ref = pos + rng.normal(0, 5e-4, (4, 2))
        a, b = fast.compute(pos, vel, ref, ref_vel, acc), reference.compute(pos, vel, ref, ref_vel,
                                                                            acc)
        np.testing.assert_allclose(a.u_unsat, b.u_unsat, rtol=1e-6, atol=1e-9)


def test_commands_stay_within_the_limit_and_finite_and_bad_inputs_give_zero():
    """Far from the reference every command is clipped to ±u_max; a NaN state or a singular
    input map gives zero torque flagged fallback; a NaN acceleration counts as zero."""
    class Singular(StiffeningModel):
        def AG(self, x):
            A, G = super().AG(x)
            G[0, 2:] = [[1.0, 2.0], [2.0, 4.0]]          # finger 0: rank 1
            return A, G
    law = SmcLaw(Singular(), 0.01, n_fingers=3, lowpass_hz=0.0)
    for seed in range(20):
        pos, vel, ref, ref_vel, acc = random_states(np.random.default_rng(seed), 3, spread=2e-2)
        acc[2] = np.nan
        pos[1, seed % 2] = np.nan
        out = law.compute(pos, vel, ref, ref_vel, ref_acc=acc)
        assert np.isfinite(out.u).all() and np.all(np.abs(out.u) <= 0.01)
        np.testing.assert_array_equal(out.u[:2], 0.0)
        np.testing.assert_array_equal(out.ok, [False, False, True])
        np.testing.assert_array_equal(out.fallback, [True, True, True])
    assert np.abs(out.u_unsat[2]).max() > 0.01 and out.saturated[2].any()


@pytest.mark.parametrize('options, match', [
    (dict(smc_lambda=0.0), 'smc_lambda'), (dict(smc_lambda=-3.0), 'smc_lambda'),
    (dict(smc_lambda=float('nan')), 'smc_lambda'), (dict(smc_k=-1.0), 'smc_k'),
    (dict(smc_k=float('inf')), 'smc_k'), (dict(smc_phi=0.0), 'smc_phi'),
    (dict(smc_phi=float('nan')), 'smc_phi'),
    (dict(pd_gains=dict(kp=1.0, kd=1.0)), "pd_gains=.* is not an option of the 'smc' law"),
    (dict(smc_k=1.0, law='pd'), "smc_k=1.0 .*the switching gain k.* is not an option of the "
                                "'pd' law; laws that take it: \\['smc'\\]"),
])
def test_bad_values_are_refused_naming_the_parameter(options, match):
    name = options.pop('law', 'smc')
    with pytest.raises(ValueError, match=match):
        make_law(name, StiffeningModel(), W, 0.05, **options)


# -- closed loop -------------------------------------------------------------------------------
def test_it_tracks_the_grasp_on_the_hands_shipped_model_in_the_in_process_loop(hand_model):
    """The in-process grasp (PyBullet hand, KF, 0.05 mm noise, the 40 Hz roll-off) under
    ``smc`` with its defaults: every finger follows its free-space reference to 0.1 mm RMS, no
    command saturates or is not finite, and it does as well as computed torque (the same
    inversion with its own tuned PD) within a factor of two."""
    from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
    from soft_gripper_sdre.control.trajectory import GraspProfile
    from soft_gripper_sdre.sim.hand import SimConfig

    def run(name):
        return run_closed_loop(make_law(name, hand_model, W, TORQUE_LIMIT), duration=0.65,
                               profile=GraspProfile(t_start=0.05, t_close=0.4, t_hold=0.15,
                                                    others='open'),
                               sim_config=SimConfig(scene='hand', noise_std=5e-5))
    smc, ct = run('smc'), run('computed_torque')
    rmse = np.array([m.rmse_mm for m in smc.metrics])
    assert np.isfinite(smc.u).all() and np.abs(smc.u).max() <= TORQUE_LIMIT
    assert not smc.saturated.any() and not smc.fallback.any()
    assert rmse.max() < 0.1, rmse
    assert rmse.max() < 2.0 * max(m.rmse_mm for m in ct.metrics)
    assert min(m.excursion_mm for m in smc.metrics) > 1.0        # the fingers did move


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_it_keeps_the_grasp_of_the_default_plan_on_the_hand(hand_model):
    """The whole default grasp in-process (close on the cube, hold, open): both grasping
    fingers touch it through the hold and it stays put, every command within the limit."""
    from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
    from soft_gripper_sdre.analysis.law_runs import score
    from soft_gripper_sdre.control.trajectory import GraspProfile
    from soft_gripper_sdre.sim.hand import SimConfig
    profile = GraspProfile()
    run = run_closed_loop(make_law('smc', hand_model, W, TORQUE_LIMIT), duration=5.5,
                          profile=profile, sim_config=SimConfig(scene='hand', noise_std=5e-5))
    s = score(run, profile)
    assert s.grasp_success and s.cube_mm < 0.2
    assert s.rmse_mm_worst < 0.1 and s.saturated_pct == 0.0
    assert np.isfinite(run.u).all() and np.abs(run.u).max() <= TORQUE_LIMIT


@pytest.mark.parametrize('shape', SHAPES, ids=SHAPE_IDS)
def test_it_tracks_a_reachable_reference_on_fingers_of_any_shape(shape):
    """The model's own response to an input within the bounds is followed to within 1 % of its
    travel, every command finite and within the bounds (one-sided ones too), unsaturated, with
    no unreachable demand where every direction is reached (a little where an input is missing:
    the model is inverted at x, not on the reference)."""
    bounds = SHAPES[shape]
    model = ShapedModel(*shape)
    law = make_law('smc', model, W, U_MAX, n_fingers=1, dt=DT, bounds=bounds)
    assert not law.io.hand and law.network is None
    reference = model_reference(model, input_signal(bounds, hz=1.0, level=0.15), seconds=0.6,
                                dt=DT)
    travel = np.abs(reference[0] - REST[:shape[0]]).max()
    errors, u, steps = track(law, model, reference, dt=DT)
    assert travel > 5e-3
    assert errors.max() < 0.01 * travel
    assert u.shape == (len(errors), shape[1])
    assert np.isfinite(u).all() and bounds.contains(u)
    assert not any(s.saturated.any() for s in steps)
    demand = np.abs(reference[2]).max()
    unreachable = max(s.unreachable[0] for s in steps)
    assert unreachable < (0.05 if shape[1] < shape[0] else 1e-9) * demand


def test_a_one_input_planar_tip_reports_the_unreachable_demand_and_does_not_chase_it():
    """(2, 1): a reference across the one input's direction cannot be followed; the step reports
    the demand outside G₂'s range, and the input is not driven into its bound chasing it."""
    model = ShapedModel(2, 1)
    law = make_law('smc', model, W, 1.0, n_fingers=1, dt=DT, bounds=InputBounds.symmetric(1.0, 1))
    g = model.G2[:, 0] / np.linalg.norm(model.G2[:, 0])
    across = np.array([-g[1], g[0]])
    w, amp = 2 * np.pi * 2.0, 5e-4
    x, unreachable, saturated, errors = np.zeros(4), [], [], []
    for k in range(400):
        t = k * DT
        p_d = REST[:2] + amp * np.sin(w * t) * across
        v_d = amp * w * np.cos(w * t) * across
        a_d = -amp * w * w * np.sin(w * t) * across
        step = law.compute((x[:2] + REST[:2])[None], x[None, 2:], p_d[None], v_d[None],
                           ref_acc=a_d[None])
        unreachable.append(step.unreachable[0])
        saturated.append(step.saturated.any())
        x = rk4(model, x, step.u[0], DT)
        errors.append(np.linalg.norm(x[:2] + REST[:2] - p_d))
    assert np.max(unreachable) > 0.1
    assert not any(saturated)
    assert np.isfinite(errors).all() and np.max(errors) < 3 * amp


@pytest.mark.parametrize('shape', SHAPES, ids=SHAPE_IDS)
def test_commands_are_finite_and_within_bounds_for_bad_states_on_any_shape(shape):
    """Finger 0 healthy, finger 1 with NaN/inf estimates and acceleration, finger 2 where the
    model's G₂ is zero: commands finite and within the bounds, step after step."""
    bounds = SHAPES[shape]
    law = make_law('smc', ShapedModel(*shape, dead_beyond=1e-3), W, U_MAX, n_fingers=3, dt=DT,
                   bounds=bounds)
    d = shape[0]
    rng = np.random.default_rng(3)
    for k in range(12):
        pos = REST[:d] + rng.normal(0.0, 5e-4, (3, d))
        pos[2, 0] = REST[0] + 2e-3
        ref = REST[:d] + rng.normal(0.0, 2e-3, (3, d))
        acc = rng.normal(0.0, 1.0, (3, d))
        pos[1, k % d] = np.nan if k % 2 else np.inf
        acc[1] = np.nan
        step = law.compute(pos, rng.normal(0.0, 1e-2, (3, d)), ref, np.zeros((3, d)),
                           ref_acc=acc)
        assert step.u.shape == (3, shape[1])
        assert np.isfinite(step.u).all() and bounds.contains(step.u)
        assert np.isfinite(step.unreachable).all()
        assert step.fallback[1] and not step.ok[1] and step.fallback[2]


# -- registry and the controller node ------------------------------------------------------------
def test_the_law_is_one_file_that_registers_itself_with_its_parameters():
    entry = LAW_REGISTRY['smc']
    assert 'smc' in GRAPH_LAWS and entry.params == SMC_PARAMS
    assert entry.options == ('smc_lambda', 'smc_k', 'smc_phi')
    assert [(p.name, p.default, p.units, p.runtime) for p in SMC_PARAMS] == [
        ('smc_lambda', SMC_DEFAULTS['lam'], '1/s', True),
        ('smc_k', SMC_DEFAULTS['k'], 'm/s²', True), ('smc_phi', SMC_DEFAULTS['phi'], 'm/s', True)]
    law = make_law('smc', StiffeningModel(), W, 0.05, smc_lambda=30.0, smc_k=2.0, smc_phi=0.01)
    assert (law.lam, law.k, law.phi) == (30.0, 2.0, 0.01)
    default = make_law('smc', StiffeningModel(), W, 0.05, smc_k=None)
    assert (default.lam, default.k, default.phi) == tuple(SMC_DEFAULTS.values())


def test_hand_over_keeps_the_command_continuous():
    model = StiffeningModel()
    old = make_law('smc', model, W, 0.05, n_fingers=2)
    pos, vel, ref, ref_vel, acc = random_states(np.random.default_rng(2), 2)
    before = old.compute(pos, vel, ref, ref_vel, acc).u
    new = make_law('smc', model, W, 0.05, n_fingers=2, smc_k=8.0)
    hand_over(old, new)
    fresh = make_law('smc', model, W, 0.05, n_fingers=2, smc_k=8.0)
    a = new.compute(pos, vel, ref, ref_vel, acc).u
    b = fresh.compute(pos, vel, ref, ref_vel, acc).u
    assert not np.allclose(a, b)                    # the roll-off starts from the old command
    alpha = new.io.roll_off.alpha
    np.testing.assert_allclose(a, alpha * before + (1 - alpha) * b, rtol=1e-12)


@pytest.mark.ros
def test_the_node_runs_smc_with_its_parameters_and_retunes_it_at_runtime(hand_model):
    """law:=smc on the controller node: the parameters come from the law's file (declared,
    ranged, runtime), the torques are the offline law's, a runtime smc_k retunes the law from the
    next estimate, a bad one is refused naming it and changes nothing; a bad smc_phi at
    start-up ends the node naming it."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    from soft_gripper_sdre.nodes import conversions as cv
    from soft_gripper_sdre.nodes.controller import PARAMS, ControllerNode
    from soft_gripper_sdre.nodes.params import ParameterError

    declared = {p.name: p for p in PARAMS}
    for p in SMC_PARAMS:
        q = declared[p.name]
        assert (q.default, q.units, q.min, q.max, q.read_only) == (p.default, p.units, p.min,
                                                                   p.max, False)
        assert q.description.startswith('smc only: ')
    rest = np.repeat(hand_model.rest_tip[None, :2], 4, 0)
    with ros_context() as (ctx, executor):
        with pytest.raises(ParameterError, match='smc_phi'):
            ControllerNode(context=ctx, parameter_overrides=overrides(law='smc', smc_phi=0.0))
        node, probe, est_pub, ref_pub = make_controller(ctx, executor, law='smc', smc_lambda=60.0,
                                                        torque_lowpass_hz=0.0)
        assert isinstance(node.tuning.law, SmcLaw) and node.tuning.law.lam == 60.0
        assert node.diag.values['smc'] == f'lambda=60 k={SMC_DEFAULTS["k"]:g} ' \
                                          f'phi={SMC_DEFAULTS["phi"]:g}'
        ref_msg, ref_pos = horizon(rest, 0, close_mm=0.05)
        ref_pub.publish(ref_msg)
        assert spin_until(executor, lambda: node.diag.counters['references'] == 1)

        def torque(k):
            send_estimate(executor, node, est_pub, estimate(k * MS, rest))
            assert spin_until(executor, lambda: len(commands(probe)) == k)
            return cv.msg_to_torques(commands(probe)[-1], 4)[1]

        client = probe.create_client(SetParameters, '/controller/set_parameters')
        assert spin_until(executor, client.service_is_ready, 20.0)

        def set_parameters(**values):
            future = client.call_async(SetParameters.Request(parameters=[
                Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]))
            assert spin_until(executor, future.done, 10.0)
            return [(r.successful, r.reason) for r in future.result().results]
        offline = make_law('smc', hand_model, W, TORQUE_LIMIT, lowpass_hz=0.0, smc_lambda=60.0)
        z = np.zeros((4, 2))
        np.testing.assert_allclose(torque(1), offline.compute(rest, z, ref_pos, z, z).u,
                                   rtol=1e-9, atol=1e-12)
        assert set_parameters(smc_k=8.0) == [(True, '')]
        retuned = make_law('smc', hand_model, W, TORQUE_LIMIT, lowpass_hz=0.0, smc_lambda=60.0,
                           smc_k=8.0)
        np.testing.assert_allclose(torque(2), retuned.compute(rest, z, ref_pos, z, z).u,
                                   rtol=1e-9, atol=1e-12)
        assert node.diag.values['smc'].startswith('lambda=60 k=8 ')
        for bad in (dict(smc_k=-1.0), dict(smc_phi=0.0), dict(smc_lambda=float('nan'))):
            ok, reason = set_parameters(**bad)[0]
            assert not ok and next(iter(bad)) in reason
        assert node.tuning.law.k == 8.0 and node.tuning.params['smc_phi'] == SMC_DEFAULTS['phi']


@pytest.fixture(scope='module')
def hand_model():
    from soft_gripper_sdre.learning.model import SDCModel
    return SDCModel()
