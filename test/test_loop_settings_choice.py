"""How the derivation chooses among its candidates (analysis/loop_settings, module doc): every
estimator intensity is tried with every integral gain; a candidate is scored by its nominal run
and the runs with the model's input gain lowered, while the runs with it raised only bound it; the
choice comes from the bandwidths whose weakest-integral loop diverged with neither the
likelihood-best intensity nor the one a decade under it. The real
laws and checks on a small SDC model of a three-tendon segment (test/chamber_models.py)."""
from collections import defaultdict
import math

from chamber_models import SHORT_PROFILE, ThreeTendons, _tendon_facts
import pytest

from soft_gripper_sdre.analysis import loop_settings as ls

BANDWIDTHS = (2.0, 4.0)
pytestmark = pytest.mark.timeout(900)


@pytest.fixture(scope='module')
def derived():
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ls, 'CHECK_PROFILE', SHORT_PROFILE)
        model = ThreeTendons()
        facts = _tendon_facts(model)
        yield model, facts, ls.derive(model, facts, bandwidths=BANDWIDTHS, workers=1)


def _by_bandwidth(rows):
    out = defaultdict(list)
    for row in rows:
        out[row['bandwidth_hz']].append(row)
    return out


def _lowered(row):
    return [r['rmse_rel'] for g, r in zip(ls.GAIN_ERRORS, row['robust']) if g < 1]


def test_every_intensity_is_tried_with_every_integral_gain(derived):
    model, facts, der = derived
    rows = _by_bandwidth(der.candidates)
    # the bandwidths given, then the best one's neighbours half an octave either side
    assert set(BANDWIDTHS) <= set(rows)
    extra = sorted(set(rows) - set(BANDWIDTHS))
    assert extra and any(extra == pytest.approx([hz / ls.REFINE_STEP, hz * ls.REFINE_STEP])
                         or extra == pytest.approx([hz / ls.REFINE_STEP])
                         or extra == pytest.approx([hz * ls.REFINE_STEP]) for hz in BANDWIDTHS)
    for hz, tried in rows.items():
        w = 2 * math.pi * hz
        want = sorted((frac * facts.accel_psd_ml, w ** 3 / div)
                      for frac in ls.ACCEL_PSD_FRACTIONS for div in ls.INTEGRAL_DIVISORS)
        got = sorted((row['accel_psd'], row['integral_gain']) for row in tried)
        assert len(got) == len(want)
        assert [v for pair in got for v in pair] == pytest.approx(
            [v for pair in want for v in pair], rel=1e-12)
        # the integral's last divisor puts k_i at eight times the loop's ω_c³
        assert max(row['integral_gain'] for row in tried) == pytest.approx(8 * w ** 3)


def test_a_candidate_is_scored_by_its_nominal_run_and_the_runs_with_the_gain_lowered(derived):
    _, _, der = derived
    scored = [row for row in der.candidates if 'robust' in row]
    assert scored
    for row in scored:
        assert row['score'] == max([row['nominal']['rmse_rel']] + _lowered(row))
    # the raised-gain runs do not enter the score where they are the worst (this model's loops
    # overshoot with the gain doubled), yet they bound the candidate
    raised = [r['rmse_rel'] for row in scored
              for g, r in zip(ls.GAIN_ERRORS, row['robust']) if g > 1]
    assert max(raised) > max(row['score'] for row in scored)
    for row in scored:
        assert row['robust_ok'] == all(r['rmse_rel'] <= ls.KEEP_ROBUST and not r['diverged']
                                       for r in row['robust'])


def test_the_choice_is_the_rule_applied_to_the_rows(derived):
    _, _, der = derived
    n = ls.MARGIN_INTENSITIES
    kept = []
    for hz, tried in _by_bandwidth(der.candidates).items():
        holds = not any(row['nominal']['diverged'] or any(r['diverged'] for r in
                                                          row.get('robust', ()))
                        for row in tried[:n])
        kept += [(row['score'], hz, row) for row in tried if holds and row.get('robust_ok')]
    assert kept
    best = min(kept, key=lambda c: c[:2])
    slower = [c for c in kept if c[1] < best[1] and c[0] <= ls.PREFER_SLOWER * best[0]]
    _, hz, row = max(slower, key=lambda c: (c[1], -c[0])) if slower else best
    chosen = der.settings
    assert (chosen.bandwidth_hz, chosen.accel_psd, chosen.integral_gain) == (
        hz, row['accel_psd'], row['integral_gain'])
    assert der.checks['sdre_ff'].rmse_rel == row['nominal']['rmse_rel']
