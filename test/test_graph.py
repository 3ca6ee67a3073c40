"""The closed loop over real DDS: all nodes in one process (launch-free harness), and as
processes."""
from graph_harness import run_graph
import numpy as np
import pytest

from soft_gripper_sdre.analysis.closed_loop import run_closed_loop
from soft_gripper_sdre.analysis.metrics import tracking_metrics
from soft_gripper_sdre.control.laws import DEFAULT_LAW, make_law
from soft_gripper_sdre.control.tracking import DEFAULT_WEIGHTS, Weights
from soft_gripper_sdre.control.trajectory import GraspProfile, GraspTrajectory
from soft_gripper_sdre.learning.model import SDCModel
from soft_gripper_sdre.sim.hand import SimConfig

pytestmark = pytest.mark.ros

#: a short grasp: close 30 mm in 0.8 s, hold 0.2 s, open in 0.8 s (the default takes 5.5 s)
SHORT = dict(t_start=0.1, t_close=0.8, t_hold=0.2, t_open=0.8)
DURATION = 2.0
LIMIT = 0.0625


@pytest.fixture(scope='module')
def graph_run():
    return run_graph(DURATION, trajectory=dict(SHORT, others='open'))


def test_graph_meets_the_free_space_tracking_target(graph_run):
    """On the shipped defaults (0.05 mm measurement noise): RMSE <= 5 % of the excursion."""
    run = graph_run
    assert run.simulator.diag.counters['timeouts'] == 0          # every period answered in lockstep
    assert run.controller.diag.counters['fallbacks'] == 0
    assert run.controller.diag.counters['check_failures'] == 0
    traj = GraspTrajectory(run.tips[0], GraspProfile(**SHORT, others='open'))
    ref = np.stack([traj.sample(t).pos for t in run.t])
    contact = np.zeros(run.tips.shape[:2], dtype=bool)
    k = np.minimum((run.t / 0.01).astype(int), len(run.contact_force) - 1)   # 100 Hz contact forces
    contact |= run.contact_force[k] > 0
    free = traj.free_space(run.t) & ~contact
    metrics = tracking_metrics(run.tips, ref, free, traj.peak_excursion())
    for i, m in enumerate(metrics):
        assert m.rmse_pct <= 5.0, f'finger {i}: {m}'
    # the two grasping fingers reach the cube, the others never do
    touching = (run.contact_force > 0).any(axis=0)
    assert touching.tolist() == [True, False, True, False]
    assert np.all(np.isfinite(run.torques)) and np.abs(run.torques).max() <= LIMIT


def test_graph_reproduces_the_in_process_loop(graph_run):
    """Topics change nothing: the node graph computes what the function-call loop computes
    (up to the horizon's Hermite interpolation of the reference, ~1e-5 m/s in velocity)."""
    noise = graph_run.simulator.p['noise_std']          # the shipped default: 0.05 mm
    assert noise == 5e-5
    assert graph_run.controller.p['law'] == DEFAULT_LAW
    model, weights = SDCModel(), Weights(**DEFAULT_WEIGHTS)
    ref = run_closed_loop(make_law(DEFAULT_LAW, model, weights, LIMIT), duration=DURATION,
                          sim_config=SimConfig(scene='hand', noise_std=noise,
                                               seed=graph_run.simulator.p['seed']),
                          profile=GraspProfile(**SHORT, others='open'))
    np.testing.assert_allclose(graph_run.t, ref.t, atol=1e-12)
    # until a finger touches the cube the two agree to micrometres; contact then amplifies the
    # reference's interpolation difference, but not beyond a fraction of the tracking error
    first_contact = int(np.argmax(ref.contact.any(axis=1)))
    assert first_contact > 500
    before = slice(0, first_contact)
    np.testing.assert_allclose(graph_run.tips[before], ref.meas[before], atol=2e-6)
    np.testing.assert_allclose(graph_run.torques[before], ref.u[before], atol=2e-4)
    np.testing.assert_allclose(graph_run.tips, ref.meas, atol=1e-4)
