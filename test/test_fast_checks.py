"""The derived settings' closed-loop checks run side by side (analysis/loop_settings.CheckRunner)
choose what one check after another chooses: the same runs, rows, messages and settings as the
search rule run serially with check_on_model (the reference written out below), on real SDC models
of a one-chamber finger and a three-tendon segment with the real laws; the BLAS thread setting of
the training tool (learning/model.set_blas_threads) set and its bad values refused."""
from dataclasses import asdict, replace
import math
import os

from chamber_models import SHORT_PROFILE, OneChamber, ThreeTendons, _chamber_facts, _tendon_facts
import numpy as np
import pytest
import scipy.linalg

from soft_gripper_sdre.analysis import loop_settings as ls
from soft_gripper_sdre.learning.model import set_blas_threads


def reference_search(runner, facts, bandwidths, rows, say, fingers=()):
    """The search rule (module doc of loop_settings) as one check after another, each with
    check_on_model (without fingers' own fits, as these tests derive)."""
    assert not fingers
    model, kept = runner.model, []

    def run(cand):
        nominal = ls.check_on_model(model, cand, facts)
        rows.append({'travel': facts.travel, 'bandwidth_hz': cand.bandwidth_hz,
                     'accel_psd': cand.accel_psd, 'integral_gain': cand.integral_gain,
                     'nominal': asdict(nominal)})
        say(f'{cand.bandwidth_hz:g} Hz, accel_psd {cand.accel_psd:.3g}, integral '
            f'{cand.integral_gain:.3g}: ' + ('diverged' if nominal.diverged else
                                            f'{100 * nominal.rmse_rel:.2f} % of travel'))
        return nominal, cand, rows[-1]

    for hz in [b for b in bandwidths if b <= ls.RATE_FRACTION / facts.period]:
        tried = [run(ls.settings_for(model, facts, hz, frac * facts.accel_psd_ml))
                 for frac in ls.ACCEL_PSD_FRACTIONS]
        if all(nominal.diverged for nominal, _, _ in tried):
            break
        w = 2 * math.pi * hz
        tried += [run(replace(cand, integral_gain=w ** 3 / divisor))
                  for _, cand, _ in list(tried) for divisor in ls.INTEGRAL_DIVISORS[1:]]
        for nominal, cand, row in tried:
            if not (nominal.ok and nominal.rmse_rel <= ls.KEEP_NOMINAL):
                continue
            runs = [ls.check_on_model(model, cand, facts, gain_error=g) for g in ls.GAIN_ERRORS]
            row['robust'] = [asdict(r) for r in runs]
            row['robust_ok'] = all(r.ok and r.rmse_rel <= ls.KEEP_ROBUST for r in runs)
            row['score'] = max([nominal.rmse_rel] + [r.rmse_rel for g, r in
                                                     zip(ls.GAIN_ERRORS, runs) if g < 1])
        if not any(nominal.diverged or any(r['diverged'] for r in row.get('robust', ()))
                   for nominal, _, row in tried[:ls.MARGIN_INTENSITIES]):
            kept += [(row['score'], hz, cand, nominal, row) for nominal, cand, row in tried
                     if row.get('robust_ok', False)]
    return kept


def _derive(model, facts, workers, bandwidths):
    said = []
    derived = ls.derive(model, facts, bandwidths=bandwidths, progress=said.append,
                        workers=workers)
    return derived, said


@pytest.mark.timeout(600)
@pytest.mark.parametrize('make_model, make_facts, bandwidths', [
    (OneChamber, lambda model: _chamber_facts(), (1.0, 2.0)),
    (ThreeTendons, _tendon_facts, (2.0, 4.0)),
])
def test_checks_side_by_side_choose_what_one_after_another_chooses(monkeypatch, make_model,
                                                                   make_facts, bandwidths):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    # four of the integral gains, the weakest and the strongest among them: the rule's order
    # is what is compared, not the number of candidates
    monkeypatch.setattr(ls, 'INTEGRAL_DIVISORS', (10.0, 2.0, 0.5, 0.125))
    model = make_model()
    facts = make_facts(model)
    parallel, said = _derive(model, facts, 2, bandwidths)
    with monkeypatch.context() as patch:
        patch.setattr(ls, '_search', reference_search)
        reference, said_reference = _derive(model, facts, 1, bandwidths)
    assert reference.settings is not None, reference.candidates
    assert len(reference.candidates) >= 10                 # several bandwidths were searched
    assert any('robust' in row for row in reference.candidates)
    # (one worker runs the same checks as two: test_the_runner_runs_checks_where_asked_...)
    assert parallel.settings == reference.settings
    assert parallel.candidates == reference.candidates      # every run's numbers, bit for bit
    assert said == said_reference
    assert parallel.checks == reference.checks
    assert parallel.paper_law == reference.paper_law
    # the default law's check of the chosen settings is the nominal run the search made, which
    # is check_on_model's result on them
    assert reference.checks['sdre_ff'] == ls.check_on_model(model, reference.settings,
                                                            reference.facts)


def test_the_runner_runs_checks_where_asked_and_the_same_everywhere(monkeypatch):
    monkeypatch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
    model, facts = OneChamber(), _chamber_facts(travel=2e-3)
    cand = ls.settings_for(model, facts, 1.0, facts.accel_psd_ml)
    results = []
    for workers in (1, 2):
        with ls.CheckRunner(model, workers) as runner:
            assert runner.workers == min(workers, os.cpu_count())
            results.append([runner.submit(cand, facts, gain_error=g).result()
                            for g in (1.0, 0.5)])
    assert results[0] == results[1]
    assert results[0][0] == ls.check_on_model(model, cand, facts)
    assert results[0][1] == ls.check_on_model(model, cand, facts, gain_error=0.5)
    assert results[0][0] != results[0][1]


@pytest.mark.parametrize('workers', [0, -1, 1.5, True, '2', None])
def test_a_bad_number_of_workers_is_refused_naming_it(workers):
    with pytest.raises(ValueError, match='workers'):
        ls.CheckRunner(OneChamber(), workers)
    with pytest.raises(ValueError, match='workers'):
        ls.derive(OneChamber(), _chamber_facts(), bandwidths=(1.0,), workers=workers)


def test_the_blas_threads_are_set_on_every_loaded_openblas():
    import ctypes
    paths = {line.split()[-1] for line in open('/proc/self/maps') if 'openblas' in line.lower()}
    if not paths:
        pytest.skip('no OpenBLAS loaded in this process')

    def counts():
        out = []
        for path in sorted(paths):
            lib = ctypes.CDLL(path)
            get = (getattr(lib, 'scipy_openblas_get_num_threads64_', None)
                   or getattr(lib, 'scipy_openblas_get_num_threads', None)
                   or getattr(lib, 'openblas_get_num_threads'))
            out.append(get())
        return out

    before = counts()
    a = np.triu(np.random.default_rng(0).random((8, 8))) + 8 * np.eye(8)
    b = np.ones((8, 3))
    x = scipy.linalg.solve_triangular(a, b)
    try:
        assert set_blas_threads(1) == len(paths)
        assert counts() == [1] * len(paths)
        assert np.array_equal(scipy.linalg.solve_triangular(a, b), x)      # the same bits
    finally:
        set_blas_threads(max(before))
    assert counts() == [max(before)] * len(paths)


@pytest.mark.parametrize('n', [0, -3])
def test_a_bad_blas_thread_count_is_refused_naming_it(n):
    with pytest.raises(ValueError, match='n must be >= 1'):
        set_blas_threads(n)
