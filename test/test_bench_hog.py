"""The CPU-hog benchmark's figures (tools/benchmarks/bench_hog.py) from a made-up /diagnostics
history."""
import math

from soft_gripper_sdre.tools.benchmarks.bench_hog import SETTLE_S, phase_figures


def window(sim_time, steps, late, p50=None, p99=None, safe=0):
    """One /diagnostics of the simulator: cumulative counters and the window's latency."""
    values = {'sim_time': f'{sim_time:.3f}', 'steps': str(steps), 'late_periods': str(late),
              'safe_periods': str(safe), 'mode': 'realtime'}
    if p50 is not None:
        values.update(recent_latency_us_p50=str(p50), recent_latency_us_p99=str(p99),
                      recent_latency_us_max=str(p99))
    return values


def test_windows_are_split_around_the_hog_and_summed_per_phase():
    history = [window(0.0, 0, 0), window(1.0, 1000, 500, 9000, 90000),     # start-up: left out
               window(3.0, 3000, 510, 1000, 2000), window(4.0, 4000, 530, 1200, 2500),
               window(5.0, 5000, 1030, 8000, 40000, safe=100),               # the hog: 4.5 … 5.2 s
               window(6.0, 6000, 1200, 3000, 9000, safe=100),
               window(7.0, 7000, 1210, 1100, 2400, safe=100),                # settling
               window(5.2 + SETTLE_S, 7200, 1212, 1100, 2400, safe=100),
               window(6.2 + SETTLE_S, 8200, 1222, 1000, 2200, safe=100),
               window(7.2 + SETTLE_S, 9200, 1232, 900, 2100, safe=100)]
    f = phase_figures(history, 4.5, 5.2)
    assert f['before'] == {'windows': 1, 'late': 0.02, 'safe': 0.0, 'p50': 1200.0, 'p99': 2500.0,
                           'max': 2500.0}
    assert f['during']['windows'] == 2 and math.isclose(f['during']['late'], 670 / 2000)
    assert f['during']['safe'] == 0.05 and f['during']['p99'] == 40000.0
    assert (f['after']['windows'] == 2 and math.isclose(f['after']['late'], 0.01)
            and f['after']['safe'] == 0.0)
    assert f['after']['p50'] == 1000.0               # the median of the windows' p50 (upper of two)


def test_a_phase_without_windows_has_no_figures():
    f = phase_figures([window(0.0, 0, 0), window(1.0, 1000, 10, 1000, 2000)], 4.5, 5.0)
    assert all(f[p]['windows'] == 0 and math.isnan(f[p]['late']) and math.isnan(f[p]['p50'])
               for p in ('before', 'during', 'after'))
