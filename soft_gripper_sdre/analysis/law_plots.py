"""The evaluation's figures: the laws against each other on one trajectory, the feedforward law
against the paper's law and the PD, and the learned model against the simulator's ground truth.

Every legend sits outside the data; the comparison a figure is for is its largest panel.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

#: an RMSE above this [mm] is drawn as a diverged run (the bar stops at the axis' end)
DIVERGED_MM = 20.0
#: bar colours: the law the figure is about, yardsticks that know the true plant, the others
HIGHLIGHT, ORACLE, OTHER = 'tab:red', '0.65', 'tab:blue'
#: trace colours of the laws drawn beside the highlighted one (none of them red)
TRACE_COLOURS = ('tab:green', 'tab:blue', 'tab:purple', 'tab:orange', 'tab:brown')


def tip_error_mm(res) -> np.ndarray:
    """(T, n) 2-D tip error of a closed-loop result [mm]."""
    return np.linalg.norm(res.pos - res.ref_pos, axis=2) * 1e3


def _is_oracle(key: str) -> bool:
    return key.startswith('oracle')


def detail_laws(scores: dict[str, tuple[float, bool]], highlight: str,
                paper: str = 'sdre') -> list[str]:
    """The laws whose traces are drawn: ``highlight``, the paper's law and the best other law (by
    RMSE) that neither knows the plant nor is a variant of ``highlight`` (``<highlight>_…``), of
    those that ran."""
    chosen = [k for k in (highlight, paper) if k in scores]
    rivals = sorted((k for k in scores if k not in chosen and not _is_oracle(k)
                     and not k.startswith(f'{highlight}_') and np.isfinite(scores[k][0])),
                    key=lambda k: scores[k][0])
    return chosen + rivals[:1]


def _bars(ax, scores: dict[str, tuple[float, bool]], labels: dict[str, str],
          highlight: str) -> None:
    """Horizontal bars of RMSE, best at the top (log scale); a lost grasp hatched, a diverged run
    drawn to the axis' end and named."""
    order = sorted(scores, key=lambda k: (not np.isfinite(scores[k][0]), scores[k][0]),
                   reverse=True)
    finite = [v for v, _ in scores.values() if np.isfinite(v) and v < DIVERGED_MM]
    lo = 10 ** np.floor(np.log10(min(finite))) if finite else 1e-2
    for row, key in enumerate(order):
        rmse, success = scores[key]
        diverged = not np.isfinite(rmse) or rmse >= DIVERGED_MM
        colour = HIGHLIGHT if key == highlight else ORACLE if _is_oracle(key) else OTHER
        ax.barh(row, DIVERGED_MM if diverged else rmse, left=0, color=colour,
                hatch='' if success else '///', edgecolor='white' if success else 'black', lw=0.5)
        text = 'diverged' if diverged else f'{rmse:.3f} mm' + ('' if success else ', grasp lost')
        ax.text(DIVERGED_MM * 0.9 if diverged else rmse * 1.08, row, text, va='center',
                ha='right' if diverged else 'left', fontsize=7,
                color='white' if diverged else 'black')
    ax.set_yticks(range(len(order)), [labels[k] for k in order], fontsize=8)
    ax.set_xscale('log')
    ax.set_xlim(lo, DIVERGED_MM * 2.5)
    ax.set_xlabel('free-space RMSE, grasping fingers [mm] (log)')
    ax.grid(axis='x', which='both', alpha=0.3)
    ax.set_title('tracking error per law (hatched: grasp lost; grey: knows the true plant)',
                 fontsize=9)


def plot_laws(results: dict, labels: dict, scores: dict[str, tuple[float, bool]], trajectory: str,
              path, highlight: str = 'sdre_ff') -> Path:
    """Every law of one trajectory. Left: each law's free-space RMSE on the grasping fingers
    (``scores``: key → (RMSE [mm], grasp success)). Right: finger 0's tip Y and tip error over
    time for the laws of :func:`detail_laws` (``results``: key → LoopResult, ``labels``: key →
    name)."""
    fig = plt.figure(figsize=(13, 5.6))
    grid = fig.add_gridspec(2, 2, width_ratios=(1.0, 1.25), hspace=0.12, wspace=0.42)
    _bars(fig.add_subplot(grid[:, 0]), scores, labels, highlight)
    ax_y = fig.add_subplot(grid[0, 1])
    ax_e = fig.add_subplot(grid[1, 1], sharex=ax_y)
    shown = detail_laws(scores, highlight)
    any_res = results[shown[0]]
    rest = any_res.ref_pos[0, 0, 1]
    ax_y.plot(any_res.t, (any_res.ref_pos[:, 0, 1] - rest) * 1e3, 'k--', lw=1.2, label='reference')
    others = iter(TRACE_COLOURS)
    for key in shown:
        res, colour = results[key], HIGHLIGHT if key == highlight else next(others)
        ax_y.plot(res.t, (res.pos[:, 0, 1] - rest) * 1e3, color=colour, lw=1, label=labels[key])
        ax_e.plot(res.t, tip_error_mm(res)[:, 0], color=colour, lw=0.9)
    ax_y.set_ylabel('finger 0 tip Y − rest [mm]')
    ax_y.tick_params(labelbottom=False)
    ax_e.set_yscale('log')
    ax_e.set_ylim(1e-3, 1e1)
    ax_e.set_ylabel('finger 0 tip error [mm]\n(in contact while closed)')
    ax_e.set_xlabel('time [s]   (true tip from the simulator)')
    ax_y.legend(loc='center', fontsize=7, framealpha=0.9)  # below the closed fingers: no data there
    fig.suptitle(f'{trajectory}: every law on the same plant, reference and noise', y=0.99)
    fig.subplots_adjust(left=0.2, right=0.98, top=0.88, bottom=0.1)
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_feedforward(results: dict, labels: dict, trajectory: str, path,
                     highlight: str = 'sdre_ff') -> Path:
    """A feedforward law (``highlight``, drawn thicker) against the others in ``results``: both
    grasping fingers' tip errors (log scale), the legend above the panels."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharex=True, sharey=True)
    others = iter(TRACE_COLOURS)
    for key, res in results.items():
        err = tip_error_mm(res)
        colour = HIGHLIGHT if key == highlight else next(others)
        for ax, finger in zip(axes, (0, 2)):
            ax.plot(res.t, err[:, finger], color=colour, lw=1.6 if key == highlight else 0.8,
                    label=labels[key], zorder=3 if key == highlight else 2)
    for ax, finger in zip(axes, (0, 2)):
        ax.set_yscale('log')
        ax.set_ylim(1e-3, 1e1)
        ax.set_xlabel('time [s]')
        ax.set_title(f'grasping finger {finger}', fontsize=9)
        ax.grid(alpha=0.3, which='major')
    axes[0].set_ylabel('tip error [mm] (in contact during the hold)')
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc='upper center', bbox_to_anchor=(0.5, 0.93), ncol=len(names),
               fontsize=8, frameon=False)
    fig.suptitle(f'{trajectory}: SDRE + model-inversion feedforward against the paper\'s law '
                 'and the PD')
    fig.tight_layout(rect=(0, 0, 1, 0.88))
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_model_vs_truth(samples: dict, path) -> Path:
    """The learned task-space acceleration against the simulator's, the exact and the projected
    one: ``samples`` holds t (T,) [s] and acc_sim, acc_exact, acc_proj, acc_learned (T, 2)
    [m/s²]."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 6.4), sharex=True)
    traces = (('acc_sim', 'simulator (measured)', dict(color='k', lw=1.2)),
              ('acc_exact', 'exact J̇q̇ + JM⁻¹(Bu − Kq − Cq̇ − g)', dict(color='C0', lw=0.9)),
              ('acc_proj', 'projected on static shapes', dict(color='C2', lw=0.9)),
              ('acc_learned', 'learned A(x)x + G(x)u', dict(color=HIGHLIGHT, lw=1.0, ls='--')))
    for i, ax in enumerate(axes):
        for key, label, style in traces:
            ax.plot(samples['t'], samples[key][:, i], label=label, **style)
        ax.set_ylabel(f'tip acceleration {"XY"[i]} [m/s²]')
        ax.grid(alpha=0.3)
    axes[1].set_xlabel('time [s]')
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc='upper center', bbox_to_anchor=(0.5, 0.94), ncol=len(names),
               fontsize=8, frameon=False)
    fig.suptitle('held-out signal u4: learned vs ground-truth task-space acceleration')
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
