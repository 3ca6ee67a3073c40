"""The one-host, two-host and link-fault runs of :mod:`soft_gripper_sdre.tools.graph.two_hosts`
side by side: tracking (each bag's report, and the two loops instant by instant), real-time
factor and loop latency, the messages each run published and recorded, and the summary the
command prints.
"""
from __future__ import annotations

import os
from pathlib import Path

from soft_gripper_sdre.tools.graph.hands import GraphRun, published_and_recorded, trouble


def timing(run: GraphRun) -> dict[str, float]:
    """Real-time factor and loop latency p50 / p99 [µs] from the simulator's final diagnostics."""
    return {'real_time_factor': run.value('simulator', 'real_time_factor'),
            'loop_latency_us_p50': run.value('simulator', 'loop_latency_us_p50'),
            'loop_latency_us_p99': run.value('simulator', 'loop_latency_us_p99'),
            'controller_compute_us': run.value('controller', 'compute_us_mean')}


def finite_torques(run: GraphRun) -> bool:
    """Whether every torque command in the run's bag is finite."""
    import numpy as np

    from soft_gripper_sdre.analysis.bag import read_bag
    msgs = read_bag(run.bag, [run.spec.topic('torque_commands')])[run.spec.topic('torque_commands')]
    return all(np.isfinite(np.asarray(m.effort, dtype=float)).all() for _, m in msgs)


def paired_tracking(one: GraphRun, two: GraphRun) -> dict:
    """The two runs instant by instant, on the instants both bags hold (a recorder starved of CPU
    for longer than a topic's 50-message history loses the oldest, on either run): whether the
    measured tips and the torque commands are bit-identical there, and each run's free-space
    tracking (:func:`~soft_gripper_sdre.analysis.metrics.tracking_metrics`) over those instants."""
    import numpy as np

    from soft_gripper_sdre.analysis.bag import extract_run
    from soft_gripper_sdre.analysis.metrics import tracking_metrics
    from soft_gripper_sdre.tools.judging.report import hold
    runs = [extract_run(run.bag) for run in (one, two)]
    common, ia, ib = np.intersect1d(runs[0].tips.t, runs[1].tips.t, return_indices=True)
    u_common, ua, ub = np.intersect1d(runs[0].torques.t, runs[1].torques.t, return_indices=True)
    out = {'instants': int(len(common)), 'steps': int(one.value('simulator', 'steps')) + 1,
           'tips_identical': bool(np.array_equal(runs[0].tips.values[ia], runs[1].tips.values[ib])),
           'torques_identical': bool(np.array_equal(runs[0].torques.values[ua],
                                                    runs[1].torques.values[ub])),
           'torque_instants': int(len(u_common))}
    for name, run, idx in (('one_host', runs[0], ia), ('two_hosts', runs[1], ib)):
        ref = run.reference.values[idx][..., :2]
        valid = np.all(np.isfinite(ref.reshape(len(ref), -1)), axis=1)
        contact = hold(run.contacts.t, run.contacts.values, common) > 0.0
        excursion = np.linalg.norm(ref[valid] - ref[valid][0], axis=2).max(axis=0)
        metrics = tracking_metrics(run.tips.values[idx][valid], ref[valid], ~contact[valid],
                                   excursion)
        out[name] = {f'finger_{i}': m.as_dict() for i, m in enumerate(metrics)}
    out['tracking_identical'] = out['one_host'] == out['two_hosts']
    return out


def compare(one: GraphRun, two: GraphRun, extra: dict, faulted: tuple[GraphRun, dict] | None,
            out: Path) -> dict:
    """The figures of the three runs side by side (tracking from each bag's report)."""
    from soft_gripper_sdre.tools.judging.report import report
    fingers = {name: report(run.bag, Path(out) / name)['fingers']
               for name, run in (('one_host', one), ('two_hosts', two))}
    result = {
        'duration_s': float(two.spec.node('simulator').parameters['duration']),
        'load_average': os.getloadavg(), 'cpus': os.cpu_count(),
        'tracking': fingers, 'report_identical': fingers['one_host'] == fingers['two_hosts'],
        'paired': paired_tracking(one, two),
        'accounts': {'one_host': published_and_recorded(one),
                     'two_hosts': published_and_recorded(two)},
        'timing': {'one_host': timing(one), 'two_hosts': timing(two)},
        'trouble': {'one_host': trouble(one), 'two_hosts': trouble(two)},
        'shared_memory': extra['shared_memory'], 'link_traffic': extra['traffic'],
    }
    if faulted is not None:
        run, fault_extra = faulted
        result['link_fault'] = {
            'fault': fault_extra['fault'], 'exit_codes': run.exit_codes,
            'steps': run.value('simulator', 'steps'),
            'timeouts': run.value('simulator', 'timeouts', 0.0),
            'safe_periods': run.value('simulator', 'safe_periods', 0.0),
            'missed_by_estimator': run.value('estimator', 'missed_periods', 0.0),
            'trouble': trouble(run), 'finite_torques': finite_torques(run),
            'published_and_recorded': published_and_recorded(run),
            'tracking': report(run.bag, Path(out) / 'link_fault')['fingers'], 'timing': timing(run)}
    return result


def summary(result: dict) -> str:
    """A short human summary of :func:`compare`'s result."""
    one, two = result['timing']['one_host'], result['timing']['two_hosts']
    worst = {k: max(f['rmse_pct'] or 0.0 for f in v.values())
             for k, v in result['tracking'].items()}
    lines = [f'{result["duration_s"]:g} s lockstep grasp; load average '
             f'{result["load_average"][0]:.1f} on {result["cpus"]} cores',
             f'  one host : {one["real_time_factor"]:.2f}× real time, loop latency p50 '
             f'{one["loop_latency_us_p50"]:.0f} µs, p99 {one["loop_latency_us_p99"]:.0f} µs; '
             f'worst finger {worst["one_host"]:.2f} %',
             f'  two hosts: {two["real_time_factor"]:.2f}× real time, loop latency p50 '
             f'{two["loop_latency_us_p50"]:.0f} µs, p99 {two["loop_latency_us_p99"]:.0f} µs; '
             f'worst finger {worst["two_hosts"]:.2f} %; '
             f'{result["link_traffic"]["tx_bytes"] / 1e6:.1f} MB sent and '
             f'{result["link_traffic"]["rx_bytes"] / 1e6:.1f} MB received over the link; '
             f'Fast DDS shared memory mapped: '
             f'{sorted(k for k, v in result["shared_memory"].items() if v) or "none"}']
    paired = result['paired']
    missing = {run: {t: n - got for t, (n, got) in accounts.items() if n is not None and n != got}
               for run, accounts in result['accounts'].items()}
    lines.append(f'  the same loop: tips '
                 f'{"identical" if paired["tips_identical"] else "DIFFERENT"} and torque '
                 f'commands {"identical" if paired["torques_identical"] else "DIFFERENT"} at the '
                 f'{paired["instants"]} of {paired["steps"]} instants both bags hold; '
                 f'tracking over them '
                 f'{"identical" if paired["tracking_identical"] else "DIFFERENT"}; report figures '
                 f'{"identical" if result["report_identical"] else "not identical"}; '
                 f'messages missing from the bags (published − recorded): {missing}')
    fault = result.get('link_fault')
    if fault:
        lost = {t: (n - got if n is not None else None)
                for t, (n, got) in fault['published_and_recorded'].items()}
        worst_fault = max(f['rmse_pct'] or 0.0 for f in fault['tracking'].values())
        lines.append(f'  link down {fault["fault"]["seconds"]:g} s at t = '
                     f'{fault["fault"]["down_sim_time"]:.2f} s: {int(fault["steps"])} steps, '
                     f'{int(fault["timeouts"])} lockstep timeouts (held command), '
                     f'{int(fault["safe_periods"])} periods stepped with zero torque for lost '
                     f'commands, {int(fault["missed_by_estimator"])} tips the estimator skipped, '
                     f'torques finite: {fault["finite_torques"]}, counters {fault["trouble"]}; '
                     f'messages lost (published − in the bag) {lost}; '
                     f'worst finger {worst_fault:.2f} %')
    return '\n'.join(lines)
