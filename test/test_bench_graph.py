"""The graph benchmarks measure what they claim: real processes over DDS, figures from the nodes."""
import pytest

from soft_gripper_sdre.tools.bench_graph import SIM_TOPICS, hop, recorder_loss, run_graph

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('raw', [False, True], ids=['typed', 'raw'])
def test_one_hop_is_timed_from_a_real_round_trip(raw):
    h = hop('events', 200, raw=raw)
    assert h['rounds'] == 200                    # every round answered (resends: h['resent'])
    assert 0 < h['p50'] <= h['p99']
    assert h['cpu'] > 0                          # the echo process did receive and send


@pytest.mark.slow
def test_lockstep_run_reports_speed_and_latency_of_every_period():
    d = run_graph(0.3)
    sim = d['simulator']
    assert sim['steps'] == 300 and sim.get('timeouts', 0) == 0
    assert sim['real_time_factor'] > 0
    assert 0 < sim['loop_latency_us_p50'] <= sim['loop_latency_us_p99'] <= sim['loop_latency_us_max']
    assert d['controller']['commands'] >= 300     # every period answered


@pytest.mark.slow
def test_recorder_keeps_every_message_with_all_topics_at_1khz():
    recorded = recorder_loss(0.3)
    for topic in SIM_TOPICS:                      # the state topics really ran at 1 kHz
        assert recorded[topic][0] == 301, recorded
    assert all(n == got for n, got in recorded.values()), recorded
