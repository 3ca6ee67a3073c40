"""How far a figure of a learned model moves with its training seed and with rounding-level changes
of its data, and where a reference model (the shipped one) lies in that spread (no ROS).

A model is a row: a dict of figures by key, with its training ``seed`` (None for the reference
model) and its data ``draw`` (0: the data as collected). Three spreads answer different questions:

* over the seeds on draw 0 — what retraining on the same data can give;
* within a seed over its draws (pooled) — what the float roundings of another CPU alone change;
* over every trained model — the range the reference model is placed in, by its z-score and by how
  many trained models lie below it.
"""
from __future__ import annotations

import math

import numpy as np


def spread(values) -> dict:
    """n, mean, sample standard deviation (ddof 1; NaN for fewer than two), min and max of the
    finite ``values``."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if v.size == 0:
        return dict(n=0, mean=float('nan'), sd=float('nan'), min=float('nan'), max=float('nan'))
    return dict(n=int(v.size), mean=float(v.mean()),
                sd=float(v.std(ddof=1)) if v.size > 1 else float('nan'),
                min=float(v.min()), max=float(v.max()))


def within_seed_sd(rows: list[dict], key: str) -> float:
    """The pooled standard deviation over the draws of each seed (the rounding-level spread alone):
    sqrt(Σ_s Σ_d (v − mean_s)² / Σ_s (n_s − 1)); NaN without a seed of two draws."""
    by_seed: dict[int, list[float]] = {}
    for r in rows:
        v = r.get(key)
        if r['seed'] is not None and v is not None and math.isfinite(v):
            by_seed.setdefault(r['seed'], []).append(v)
    ss = sum(float(np.sum((np.asarray(v) - np.mean(v)) ** 2)) for v in by_seed.values())
    dof = sum(len(v) - 1 for v in by_seed.values())
    return math.sqrt(ss / dof) if dof > 0 else float('nan')


def summarise(rows: list[dict], keys) -> dict:
    """Per figure (``keys``: (key, label, format) tuples): the spread over seeds on the collected
    data (draw 0), the pooled spread over the draws of one seed, the spread over every trained
    model, and the reference model's value with its place among the trained models (z-score
    against all, and how many lie below it)."""
    trained = [r for r in rows if r['seed'] is not None]
    draw0 = [r for r in trained if r['draw'] == 0]
    shipped = next((r for r in rows if r['seed'] is None), None)
    out = {}
    for key, _, _ in keys:
        every = spread(r.get(key) for r in trained)
        entry = {'seeds': spread(r.get(key) for r in draw0),
                 'draws_sd': within_seed_sd(trained, key), 'all': every}
        if shipped is not None and shipped.get(key) is not None:
            v = shipped[key]
            values = [r[key] for r in trained if r.get(key) is not None and math.isfinite(r[key])]
            entry['shipped'] = {'value': v,
                                'z': (v - every['mean']) / every['sd']
                                     if every['sd'] and every['sd'] > 0 else float('nan'),
                                'below': sum(x < v for x in values), 'of': len(values)}
        out[key] = entry
    return out
