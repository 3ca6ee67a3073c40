"""bag.extract_run and the report tool on a synthetic run with known errors, recorded as a real bag.

The run (4 fingers, 1 ms tips from t = 0 to 0.499 s) is built with conversions.py, published over
DDS and written by the recorder node, as in the demo. (rclpy's serialize_message pads its output
with a few garbage bytes that rosbags refuses, so DDS is also the simplest way to exact CDR.)
The reference starts at 10 ms (earlier tip samples are not scored) and is piecewise linear with
kinks on its 10 ms horizon points, so interpolating the horizon reproduces it exactly.
"""
import json
import os
from pathlib import Path
import subprocess
import sys

from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from rosutil import Probe, overrides, ros_context, spin_until

from soft_gripper_sdre.analysis.bag import BagError, extract_run, read_bag, sample_reference
from soft_gripper_sdre.nodes import conversions as cv
from soft_gripper_sdre.nodes.recorder import RecorderNode, topic_qos
from soft_gripper_sdre.nodes.topics import TOPIC_TYPES
from soft_gripper_sdre.tools.judging import report as report_tool

pytestmark = pytest.mark.ros

MS = 1_000_000
T_TIPS = np.arange(500) * MS                       # tip samples [ns]
REF_STAMPS = np.arange(10, 500, 20) * MS           # 25 horizons of 11 points, 10 ms apart
STATE_STAMPS = np.arange(0, 500, 10) * MS          # cube contacts and pose at 100 Hz
BASE = np.array([[0.00, 0.05], [0.01, 0.05], [0.02, 0.05], [0.03, 0.05]])
AMPLITUDE = np.array([[0.0, 0.020], [0.010, 0.0], [0.0, 0.020], [0.0, 0.0]])   # finger 3 stays put
CONTACT = (100 * MS, 200 * MS)                     # finger 1 touches the cube (force held 10 ms)
LIMIT = 0.1


def tri(t_ns):
    """Up over 0.2 s, down over 0.2 s, then 0; kinks at 0.2 and 0.4 s."""
    t = np.asarray(t_ns) / 1e9
    return np.clip(np.minimum(t / 0.2, (0.4 - t) / 0.2), 0.0, None)


def dtri(t_ns):
    t = np.asarray(t_ns) / 1e9
    return np.where(t < 0.2, 5.0, np.where(t < 0.4, -5.0, 0.0))


def ref_state(t_ns):
    """(…, 4, 2) reference position and velocity."""
    t_ns = np.asarray(t_ns)
    pos = BASE + tri(t_ns)[..., None, None] * AMPLITUDE
    vel = dtri(t_ns)[..., None, None] * AMPLITUDE
    return pos, vel


def in_contact(t_ns):
    return (t_ns >= CONTACT[0]) & (t_ns < CONTACT[1])


def tip_error(t_ns):
    """Known error: finger 0 1 mm in X; finger 1 1 mm in Y (10 mm in contact); 2 none; 3 0.5 mm."""
    err = np.zeros((4, 2))
    err[0, 0] = 1e-3
    err[1, 1] = 10e-3 if in_contact(t_ns) else 1e-3
    err[3, 1] = 0.5e-3
    return err


def torques(t_ns):
    u = np.full((4, 2), 0.05)
    if t_ns < 60 * MS:
        u[0, 0] = LIMIT                              # saturated: 50 samples from 10 ms on
    if t_ns == 300 * MS:
        u[2, 1] = -1.2 * LIMIT
    return u


def cube_pose_msg(ns):
    msg = PoseStamped()
    msg.header.stamp = cv.to_time(ns)
    p = msg.pose.position
    p.x, p.y, p.z = (0.103, 0.204, 0.3) if ns >= 250 * MS else (0.1, 0.2, 0.3)
    msg.pose.orientation.w = 1.0
    return msg


def write_bag(path: Path, messages: dict[str, list], batch: int = 25) -> None:
    """Record ``{topic: [msg, ...]}``: publish to a RecorderNode in batches well within the
    queues."""
    with ros_context() as (ctx, executor):
        rec = RecorderNode(context=ctx,
                           parameter_overrides=overrides(output=str(path), topics=list(messages)))
        probe = Probe(ctx)
        pubs = {t: probe.create_publisher(TOPIC_TYPES[t], t, topic_qos(t)) for t in messages}
        executor.add_node(rec)
        executor.add_node(probe)
        assert spin_until(executor,
                          lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 20.0)
        for topic, msgs in messages.items():
            for start in range(0, len(msgs), batch):
                for msg in msgs[start:start + batch]:
                    pubs[topic].publish(msg)
                n = min(start + batch, len(msgs))
                assert spin_until(executor, lambda: rec.counts['/' + topic] == n, 10.0), topic
        rec.close()


def run_messages() -> dict[str, list]:
    tips, estimates = [], []
    for ns in T_TIPS:
        pos_d, vel_d = ref_state(ns)
        pos = pos_d + tip_error(ns)
        tips.append(cv.tips_to_msg(ns, np.column_stack([pos, np.zeros(4)])))
        estimates.append(cv.estimate_to_msg(ns, pos, vel_d))
    commands = [cv.torques_to_msg(ns, torques(ns)) for ns in T_TIPS]
    bad = cv.torques_to_msg(5 * MS, torques(0))
    bad.name = ['finger_9/ax0'] + bad.name[1:]                                   # skipped
    refs = []
    for ns in REF_STAMPS:
        offsets = np.arange(11) * 10 * MS
        pos_d, vel_d = ref_state(ns + offsets)
        refs.append(cv.reference_to_msg(ns, offsets, pos_d, vel_d, np.zeros_like(pos_d)))
    contacts = [cv.contacts_msg(ns, [0.0, 2.0 if in_contact(ns) else 0.0, 0.0, 0.0])
                for ns in STATE_STAMPS]
    return {'tip_positions': tips, 'state_estimate': estimates, 'torque_commands': commands + [bad],
            'grasp_reference': refs, 'cube_contacts': contacts,
            'cube_pose': [cube_pose_msg(ns) for ns in STATE_STAMPS]}


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp('report') / 'run'
    write_bag(path, run_messages())
    return path


def test_extract_run_gives_the_arrays_that_were_written(bag):
    run = extract_run(bag)
    assert run.n_fingers == 4
    np.testing.assert_array_equal(run.tips.t, T_TIPS / 1e9)
    assert run.tips.values.shape == (500, 4, 2) and run.estimate.values.shape == (500, 4, 4)
    assert run.torques.values.shape == (500, 4, 2) and run.skipped == {'torque_commands': 1}
    assert run.contacts.values.shape == (50, 4) and run.cube_pose.values.shape == (50, 7)
    ref = run.reference.values
    assert np.isnan(ref[:10]).all()                                 # before the first horizon
    pos_d, vel_d = ref_state(T_TIPS[10:])
    np.testing.assert_allclose(ref[10:, :, :2], pos_d, atol=1e-12)
    on_points = (T_TIPS[10:] % (10 * MS)) == 0                      # velocity kinks lie between
                                                                    # points
    np.testing.assert_allclose(ref[10:, :, 2:][on_points], vel_d[on_points], atol=1e-12)
    assert run.counts['/tip_positions'] == 500 and run.counts['/torque_commands'] == 501


def test_sample_reference_uses_the_latest_horizon_and_interpolates():
    first = (np.array([0, 10, 20]) * MS, np.zeros((3, 1, 4)))
    second = (np.array([5, 15]) * MS, np.array([[[1.0, 2.0, 3.0, 4.0]], [[3.0, 4.0, 5.0, 6.0]]]))
    t = np.array([-1, 0, 4, 5, 10, 15, 30]) * MS
    out = sample_reference(t, np.array([0, 5]) * MS, [first, second])
    assert np.isnan(out[0]).all()
    np.testing.assert_array_equal(out[1:3, 0], 0.0)                 # only the first is in force
    np.testing.assert_allclose(out[3:, 0, 0], [1.0, 2.0, 3.0, 3.0])  # then the second, held at
                                                                     # its end


def test_report_metrics_match_the_errors_built_in(bag, tmp_path):
    m = report_tool.report(bag, tmp_path / 'out', torque_limit=LIMIT)
    f = m['fingers']
    assert m['samples'] == 490 and m['start_s'] == pytest.approx(0.010)
    assert (f['finger_0']['rmse_mm'] == pytest.approx(1.0)
            and f['finger_0']['max_mm'] == pytest.approx(1.0))
    # excursion from the reference's first point (1 mm up the ramp at 10 ms) to its 20 mm peak
    assert f['finger_0']['excursion_mm'] == pytest.approx(19.0)
    assert f['finger_0']['rmse_pct'] == pytest.approx(100.0 / 19.0)
    # finger 1: the 10 mm error in contact is not free space
    assert (f['finger_1']['rmse_mm'] == pytest.approx(1.0)
            and f['finger_1']['max_mm'] == pytest.approx(1.0))
    assert (f['finger_1']['samples'] == 390
            and f['finger_1']['contact_fraction'] == pytest.approx(100 / 490))
    assert f['finger_2']['rmse_mm'] == pytest.approx(0.0, abs=1e-9)
    assert f['finger_3']['rmse_mm'] == pytest.approx(0.5) and f['finger_3']['rmse_pct'] is None
    assert all(f[name]['contact_fraction'] == 0.0 for name in ('finger_0', 'finger_2', 'finger_3'))
    assert m['cube_max_displacement_mm'] == pytest.approx(5.0)
    assert m['torque_saturation']['saturated'] == {'finger_0': 50, 'finger_1': 0, 'finger_2': 1,
                                                   'finger_3': 0}
    assert m['message_counts']['/grasp_reference'] == 25 and m['message_counts']['/cube_pose'] == 50
    assert m['skipped_messages'] == {'torque_commands': 1}
    assert json.loads((tmp_path / 'out' / 'metrics.json').read_text()) == m


def test_report_without_contacts_scores_every_sample(tmp_path):
    messages = run_messages()
    del messages['cube_contacts'], messages['cube_pose']
    write_bag(tmp_path / 'run', messages)
    m = report_tool.report(tmp_path / 'run', tmp_path / 'out')
    rmse_1 = np.sqrt((100 * 10.0**2 + 390 * 1.0**2) / 490)
    assert m['fingers']['finger_1']['rmse_mm'] == pytest.approx(rmse_1)
    assert m['fingers']['finger_1']['contact_fraction'] is None
    assert m['cube_max_displacement_mm'] is None and m['torque_saturation'] is None


def test_report_cli_writes_real_pngs_and_metrics(bag, tmp_path):
    out = tmp_path / 'figs'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.judging.report', str(bag),
                           '--out', str(out), '--torque-limit', str(LIMIT)],
                          env=dict(os.environ), capture_output=True, text=True, timeout=50)
    assert proc.returncode == 0, proc.stderr
    assert 'finger_0: RMSE 1.000 mm' in proc.stdout
    for name in report_tool.FIGURES:
        data = (out / name).read_bytes()
        assert data.startswith(b'\x89PNG\r\n\x1a\n') and len(data) > 10_000, name
    metrics = json.loads((out / report_tool.METRICS).read_text())
    assert metrics['fingers']['finger_0']['rmse_mm'] == pytest.approx(1.0)


def test_report_cli_bad_bag_exits_2(tmp_path):
    missing = tmp_path / 'no_such_bag'
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.judging.report',
                           str(missing), '--out', str(tmp_path / 'out')], env=dict(os.environ),
                          capture_output=True, text=True, timeout=50)
    assert proc.returncode == 2 and str(missing) in proc.stderr and 'does not exist' in proc.stderr


def test_bad_bags_are_named_in_the_error(tmp_path, capsys):
    (tmp_path / 'empty').mkdir()
    assert report_tool.main([str(tmp_path / 'empty'), '--out', str(tmp_path / 'out')]) == 2
    assert 'no metadata.yaml' in capsys.readouterr().err
    (tmp_path / 'broken').mkdir()
    (tmp_path / 'broken' / 'metadata.yaml').write_text('rosbag2_bagfile_information: [\n')
    with pytest.raises(BagError, match='broken.*cannot be read'):
        read_bag(tmp_path / 'broken')
    messages = run_messages()
    write_bag(tmp_path / 'tips_only', {'tip_positions': messages['tip_positions']})
    with pytest.raises(BagError,
                       match=r'tips_only lacks topic\(s\) state_estimate, grasp_reference'):
        extract_run(tmp_path / 'tips_only')
    with pytest.raises(BagError, match='no topic'):
        read_bag(tmp_path / 'tips_only', ['grasp_reference'])
