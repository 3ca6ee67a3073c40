"""The hand kernel decides A_cl's stability by its eigenvalues where its Lyapunov proof fails
(control/kernels/riccati.finger_checks): a slow loop's weights (q_vel = 0, the derived settings'
0.5–2 Hz) keep the warm-started Newton–Kleinman solution instead of handing every period to scipy,
with the torques scipy's exact solution gives to the solver's tolerance."""
import numpy as np
import pytest

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.control.laws import make_law
from soft_gripper_sdre.learning.model import DEFAULT_MODEL, SDCModel, set_blas_threads


@pytest.mark.parametrize('bandwidth', [0.5, 1.0])
def test_a_slow_loop_keeps_its_warm_solutions(bandwidth):
    set_blas_threads(1)
    model = SDCModel(DEFAULT_MODEL)
    facts = ls.DataFacts(period=5e-3, noise_std=2e-5, travel=2e-3, torque_limit=0.02,
                         accel_psd_ml=1.0, direction=90.0)
    settings = ls.settings_for(model, facts, bandwidth, 1.0)
    laws = {method: make_law('sdre', model, settings.weights(), settings.torque_limit,
                             n_fingers=1, method=method, dt=facts.period, lowpass_hz=0.0)
            for method in ('fast', 'reference')}
    rest = np.asarray(model.rest_tip, float)[:2]
    rng = np.random.default_rng(0)
    worst, scale = 0.0, 0.0
    for k in range(200):
        pos = rest[None] + 1e-3 * np.sin(0.05 * k) + 2e-5 * rng.standard_normal((1, 2))
        vel = 1e-3 * np.cos(0.05 * k) * np.ones((1, 2))
        ref = rest[None] + np.array([[0.0, 1e-3]])
        u = {m: law.compute(pos, vel, ref, np.zeros((1, 2))).u for m, law in laws.items()}
        worst = max(worst, float(np.abs(u['fast'] - u['reference']).max()))
        scale = max(scale, float(np.abs(u['reference']).max()))
    # the first, cold period is solved exactly; every later one is the kernel's own
    assert laws['fast'].sdre.exact_solves == 1
    assert scale > 0 and worst <= 1e-5 * scale
