"""Computed torque on the learned model and the default law's integral action, against closed
forms."""
import numpy as np
import pytest
from sdc_models import REST, StiffeningModel, track_sine

from soft_gripper_sdre.control.laws import (
    DEFAULT_INTEGRAL,
    GRAPH_LAWS,
    ComputedTorqueLaw,
    IntegralAction,
    SdreFeedforwardLaw,
    make_law,
)
from soft_gripper_sdre.control.laws.integral import INTEGRAL_LEAK_S
from soft_gripper_sdre.control.tracking import Weights
from soft_gripper_sdre.learning.model import SDCModel

W = Weights(1e6, 0.0, 1.6e4)
G2 = np.array([[15.0, 640.0], [-620.0, -8.0]])


def random_states(rng, n, spread=3e-3):
    pos = REST[:2] + rng.normal(0, spread, (n, 2))
    return (pos, rng.normal(0, 0.05, (n, 2)), pos + rng.normal(0, 1e-3, (n, 2)),
            rng.normal(0, 0.05, (n, 2)), rng.normal(0, 1.0, (n, 2)))


# -- computed torque ---------------------------------------------------------------------------
def test_computed_torque_makes_the_models_tip_acceleration_the_pd_acceleration():
    """Unsaturated: A₂(x)x + G₂(x)u = a_d − k_p e − k_d ė exactly, at random states of a
    state-dependent model."""
    model = StiffeningModel()
    law = ComputedTorqueLaw(model, 1e9, kp=1.2e4, kd=70.0, n_fingers=5, lowpass_hz=0.0)
    for seed in range(20):
        pos, vel, ref, ref_vel, ref_acc = random_states(np.random.default_rng(seed), 5)
        out = law.compute(pos, vel, ref, ref_vel, ref_acc=ref_acc)
        x = np.concatenate([pos - REST[:2], vel], 1)
        A, G = model.AG(x)
        acc = np.einsum('nij,nj->ni', A[:, 2:], x) + np.einsum('nij,nj->ni', G[:, 2:], out.u)
        want = ref_acc - 1.2e4 * (pos - ref) - 70.0 * (vel - ref_vel)
        np.testing.assert_allclose(acc, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
        assert out.ok.all() and not out.fallback.any() and not out.saturated.any()


def test_computed_torque_saturates_and_rolls_off_like_every_law():
    """Property over random states: u = clip(u_unsat, ±u_max) without roll-off, saturated where
    |u_unsat| > u_max, always finite; with the roll-off, the first-order filter of that."""
    model = StiffeningModel()
    plain = ComputedTorqueLaw(model, 0.01, n_fingers=6, lowpass_hz=0.0)
    rolled = ComputedTorqueLaw(model, 0.01, n_fingers=6, lowpass_hz=40.0, dt=1e-3)
    a = np.exp(-2 * np.pi * 40.0 * 1e-3)
    previous = None
    for seed in range(30):
        args = random_states(np.random.default_rng(seed), 6, spread=2e-2)
        out = plain.compute(*args[:4], ref_acc=args[4])
        assert np.all(np.isfinite(out.u)) and np.all(np.abs(out.u) <= 0.01)
        np.testing.assert_array_equal(out.u, np.clip(out.u_unsat, -0.01, 0.01))
        np.testing.assert_array_equal(out.saturated, np.abs(out.u_unsat) > 0.01)
        r = rolled.compute(*args[:4], ref_acc=args[4]).u
        np.testing.assert_allclose(r, out.u if previous is None else a * previous + (1 - a) * out.u,
                                   rtol=1e-12)
        previous = r
    assert out.saturated.any()


def test_computed_torque_with_a_singular_input_map_or_bad_inputs_gives_zero_torque_and_says_so():
    class Singular(StiffeningModel):
        def AG(self, x):
            A, G = super().AG(x)
            G[0, 2:] = [[1.0, 2.0], [2.0, 4.0]]          # finger 0: rank 1
            return A, G
    law = ComputedTorqueLaw(Singular(), 0.05, n_fingers=3, lowpass_hz=0.0)
    pos, vel, ref, ref_vel, acc = random_states(np.random.default_rng(3), 3)
    acc[2] = np.nan
    out = law.compute(pos, vel, ref, ref_vel, ref_acc=acc)
    np.testing.assert_array_equal(out.u[0], 0.0)
    np.testing.assert_array_equal(out.ok, [False, True, True])
    np.testing.assert_array_equal(out.fallback, [True, False, True])  # finger 2: a_d counted as 0
    pos[1] = np.nan
    out = law.compute(pos, vel, ref, ref_vel)
    np.testing.assert_array_equal(out.u[1], 0.0)
    assert not out.ok[1] and out.fallback[1]
    with pytest.raises(ValueError, match='kp'):
        ComputedTorqueLaw(StiffeningModel(), 0.05, kp=0.0)
    with pytest.raises(ValueError, match=r'must each have shape \(3, 2\)'):
        law.compute(pos[:2], vel[:2], ref[:2], ref_vel[:2])


def test_computed_torque_compiled_path_matches_the_model_on_the_shipped_network():
    model = SDCModel()
    fast = make_law('computed_torque', model, W, 0.0625, lowpass_hz=0.0)
    reference = make_law('computed_torque', model, W, 0.0625, lowpass_hz=0.0, method='reference')
    assert fast.network is not None and reference.network is None
    rng = np.random.default_rng(7)
    for _ in range(5):
        pos = model.rest_tip[:2] + rng.normal(0, 5e-3, (4, 2))
        vel, ref_vel, acc = (rng.normal(0, 0.05, (4, 2)), rng.normal(0, 0.05, (4, 2)),
                             rng.normal(0, 1, (4, 2)))
        ref = pos + rng.normal(0, 5e-4, (4, 2))
        a, b = (fast.compute(pos, vel, ref, ref_vel, acc),
                reference.compute(pos, vel, ref, ref_vel, acc))
        np.testing.assert_allclose(a.u_unsat, b.u_unsat, rtol=1e-6, atol=1e-9)


def test_computed_torque_is_a_graph_law_with_pd_gains():
    assert 'computed_torque' in GRAPH_LAWS
    law = make_law('computed_torque', StiffeningModel(), W, 0.06, pd_gains=dict(kp=5e3, kd=20.0))
    assert isinstance(law, ComputedTorqueLaw) and (law.kp, law.kd) == (5e3, 20.0)
    with pytest.raises(ValueError,
                       match="integral_gain=.* is not an option of the 'computed_torque' law"):
        make_law('computed_torque', StiffeningModel(), W, 0.06, integral_gain=1.0)


def test_computed_torque_tracks_a_sinusoid_on_a_state_dependent_model():
    """Closed loop on the model itself (RK4, 0.2 ms hold), started on a 4 mm sine: the error stays
    at the zero-order hold's."""
    model, dt = StiffeningModel(), 2e-4
    law = ComputedTorqueLaw(model, 1e9, n_fingers=1, lowpass_hz=0.0, dt=dt)
    worst = track_sine(law, model, seconds=0.3, dt=dt)
    assert worst < 1e-5


# -- integral action ---------------------------------------------------------------------------
def test_integral_integrates_inside_the_band_and_freezes_while_saturated():
    ia = IntegralAction(G2, gain=1e5, band=5e-4, u_max=0.05, n_fingers=3, dt=1e-3)
    err = np.array([[1e-4, 0.0], [0.0, -2e-4], [1e-4, 1e-4]])
    sat = np.array([[False, False], [False, False], [True, False]])
    for _ in range(10):
        ia.update(err, sat, np.ones(3, dtype=bool))
    np.testing.assert_allclose(ia.xi[:2], -10 * 1e-3 * err[:2], rtol=1e-12)  # ξ = ∫(p_d − p)dt
    np.testing.assert_array_equal(ia.xi[2], 0.0)                             # saturated: frozen
    np.testing.assert_allclose(G2 @ ia.torque()[1], 1e5 * ia.xi[1], rtol=1e-12,
                               atol=1e-15)                                   # u_I = k_i G₂⁻¹ ξ
    before = ia.xi.copy()
    ia.update(err, np.ones((3, 2), dtype=bool), np.ones(3, dtype=bool))      # all saturated
    np.testing.assert_array_equal(ia.xi, before)
    ia.update(np.full((3, 2), np.nan), np.zeros((3, 2), dtype=bool), np.zeros(3, dtype=bool))
    np.testing.assert_array_equal(ia.xi, before)                             # non-finite: untouched
    ia.reset()
    np.testing.assert_array_equal(ia.xi, 0.0)


def test_integral_decays_outside_the_band_and_is_bounded_by_the_torque_limit():
    ia = IntegralAction(G2, gain=1e5, band=5e-4, u_max=0.05, n_fingers=2, dt=1e-3)
    free = np.zeros((2, 2), dtype=bool)
    for _ in range(200):
        ia.update(np.array([[0.0, 4e-4], [0.0, 0.0]]), free, np.ones(2, dtype=bool))
    built = ia.xi[0].copy()
    assert built[1] < 0 and built[0] == 0.0
    for _ in range(100):                                       # pressing on the cube: 1 mm of error
        ia.update(np.array([[0.0, 1e-3], [0.0, 0.0]]), free, np.ones(2, dtype=bool))
    np.testing.assert_allclose(ia.xi[0], built * np.exp(-0.1 / INTEGRAL_LEAK_S), rtol=1e-9)
    wind = IntegralAction(G2, gain=1e5, band=1.0, u_max=0.05, n_fingers=1, dt=1e-3)
    for _ in range(100000):                                    # a large error held for 100 s
        wind.update(np.array([[0.2, -0.3]]), np.zeros((1, 2), dtype=bool), np.ones(1, dtype=bool))
    assert (np.all(np.abs(wind.torque()) <= 0.05 * (1 + 1e-12))
            and np.abs(wind.torque()).max() > 0.049)
    with pytest.raises(ValueError, match='gain'):
        IntegralAction(G2, gain=np.inf, band=1e-3, u_max=0.05, n_fingers=1, dt=1e-3)
    with pytest.raises(ValueError, match='band'):
        IntegralAction(G2, gain=1.0, band=0.0, u_max=0.05, n_fingers=1, dt=1e-3)
    with pytest.raises(ValueError, match='invertible'):
        IntegralAction(np.ones((2, 2)), gain=1.0, band=1e-3, u_max=0.05, n_fingers=1, dt=1e-3)


def spring_model():
    from types import SimpleNamespace
    A = np.zeros((4, 4))
    A[0, 2] = A[1, 3] = 1.0
    A[2:, :2] = -np.diag([300.0, 900.0])
    G = np.zeros((4, 2))
    G[2:] = G2
    return SimpleNamespace(rest_tip=REST,
                           AG=lambda x: (np.broadcast_to(A, (len(np.atleast_2d(x)), 4, 4)).copy(),
                                         np.broadcast_to(G, (len(np.atleast_2d(x)), 4, 2)).copy()))


@pytest.mark.parametrize('method', ['fast', 'reference'])
def test_default_law_adds_the_integral_and_stops_integrating_at_the_torque_limit(method):
    """A constant error inside the band: each step's torque grows by k_i Δt G₂⁻¹(p_d − p) over the
    law without integral; once the command saturates the integral stops growing; reset() forgets
    it."""
    model = spring_model()
    kw = dict(n_fingers=1, lowpass_hz=0.0, method=method)
    with_i = SdreFeedforwardLaw(model, W, 1e9, integral_gain=1e5, **kw)
    without = SdreFeedforwardLaw(model, W, 1e9, integral_gain=0.0, **kw)
    assert without.integral is None
    pos, z = REST[None, :2].copy(), np.zeros((1, 2))
    ref = pos + [[0.0, 2e-4]]
    for k in range(5):
        du = with_i.compute(pos, z, ref, z).u - without.compute(pos, z, ref, z).u
        np.testing.assert_allclose(G2 @ du[0], 1e5 * k * 1e-3 * np.array([0.0, 2e-4]), rtol=1e-6,
                                   atol=1e-12)
    with_i.reset()
    np.testing.assert_allclose(with_i.compute(pos, z, ref, z).u, without.compute(pos, z, ref, z).u,
                               rtol=1e-9)
    tight = SdreFeedforwardLaw(model, W, 1e-3, integral_gain=1e5, **kw)  # saturated from the start
    for _ in range(50):
        out = tight.compute(pos, z, ref, z)
    assert out.saturated.any() and np.all(tight.integral.xi == 0.0)


def test_integral_is_the_default_laws_switch():
    law = make_law('sdre_ff', spring_model(), W, 0.06)
    assert law.integral is not None and law.integral.gain == DEFAULT_INTEGRAL['gain'] > 0
    assert make_law('sdre_ff', spring_model(), W, 0.06, integral_gain=0.0).integral is None
    assert make_law('sdre_ff', spring_model(), W, 0.06, integral_band=1e-3).integral.band == 1e-3
    with pytest.raises(ValueError, match='integral_gain'):
        make_law('sdre_ff', spring_model(), W, 0.06, integral_gain=-1.0)


def test_the_compiled_integral_and_roll_off_are_the_separate_steps_bit_for_bit():
    """The default law's fast path ends in one compiled call (integral, saturation, roll-off): on
    the shipped model, at states inside and outside the band, saturated and not, with the
    roll-off on and off, its torques, saturation, integral and filter state are those of
    IntegralAction.apply followed by RollOff, bit for bit."""
    model = SDCModel()
    rng = np.random.default_rng(3)
    for lowpass_hz, u_max in ((40.0, 0.0625), (40.0, 0.004), (0.0, 0.0625)):
        fused, split = (SdreFeedforwardLaw(model, Weights(1e6, 0.0, 1.6e4), u_max,
                                           lowpass_hz=lowpass_hz)
                        for _ in range(2))
        saturated = outside = 0
        for k in range(300):
            pos = model.rest_tip[:2] + rng.normal(0, 2e-3, (4, 2))
            spread = 2e-4 if k % 3 else 2e-3                   # inside the 0.5 mm band, and outside
            args = (pos, rng.normal(0, 0.02, (4, 2)), pos + rng.normal(0, spread, (4, 2)),
                    rng.normal(0, 0.02, (4, 2)), rng.normal(0, 0.5, (4, 2)))
            a = fused.compute(*args)
            z = split.io.frame.stacked(*args)
            b = split.sdre.track_feedforward(split.network, split.io.origin, False, z)
            split.integral.apply(b, z[:, 0:2] - z[:, 4:6], split.sdre.feedforward.state_finite)
            b.u = split.io.roll_off(b.u)
            for name in ('u', 'u_unsat', 'saturated'):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name),
                                              err_msg=f'{name}, step {k}')
            np.testing.assert_array_equal(fused.integral.xi, split.integral.xi, err_msg=f'step {k}')
            saturated += int(a.saturated.any())
            outside += int((np.linalg.norm(args[0] - args[2], axis=1) > fused.integral.band).any())
        assert outside > 50 and (saturated > 50 if u_max < 0.01 else saturated < 300)
        if lowpass_hz:
            assert a.u is fused.io.roll_off._u  # the filter goes on from this step's output
            assert not np.array_equal(a.u, np.clip(a.u_unsat, -u_max, u_max))
