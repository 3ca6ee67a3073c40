"""The paper's figures (training loss 2, predicted vs true acceleration 3, tracking 5–7) and the
gain sweep; the evaluation's comparisons are in :mod:`soft_gripper_sdre.analysis.law_plots`.

Input is plain arrays (SI) or closed-loop results, so the same functions draw an in-process run and
a recorded bag.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

AXES = ('X', 'Y')


def _span_limits(ax, values: np.ndarray, min_span: float) -> None:
    """Y limits around the data with at least ``min_span`` of range, so a nearly constant trace is
    not blown up to its noise."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return
    lo, hi = float(finite.min()), float(finite.max())
    pad = max(min_span - (hi - lo), 0.0) / 2 + 0.08 * max(hi - lo, min_span)
    ax.set_ylim(lo - pad, hi + pad)


def plot_tracking(t_ref, ref, t_act, act, path, *, quantity: str, achieved_label: str, title: str,
                  finger_names=None, contact=None) -> Path:
    """Desired vs achieved per finger: X and Y beside each other, the 2-D error on its own axis.

    Args:
        t_ref, ref: (T,) [s] and (T, n, 2) desired values [m or m/s].
        t_act, act: (S,) and (S, n, 2) achieved values on their own time base.
        quantity: ``'position'`` (mm, relative to the reference's first point) or ``'velocity'``.
        achieved_label: legend entry of the achieved trace (says which signal it is).
        contact: (T,) … (T, n) bool on ``t_ref``, shaded where the finger touches the cube.
    """
    ref, act = np.asarray(ref, dtype=float), np.asarray(act, dtype=float)
    t_ref, t_act = np.asarray(t_ref, dtype=float), np.asarray(t_act, dtype=float)
    n = ref.shape[1]
    names = finger_names or [f'finger_{i}' for i in range(n)]
    position = quantity == 'position'
    origin = ref[0] if position else np.zeros_like(ref[0])
    unit, min_span = ('mm', 2.0) if position else ('mm/s', 10.0)
    desired_on_act = np.stack([np.stack([np.interp(t_act, t_ref, ref[:, i, a])
                                         for a in range(2)], -1)
                               for i in range(n)], 1)
    error = 1e3 * np.linalg.norm(act - desired_on_act, axis=2)                # (S, n)
    # the error axes are scaled to free space: in contact the reference lies inside the cube,
    # off that scale on purpose
    free = np.ones((len(t_act), n), dtype=bool)
    if contact is not None:
        free = ~contact[np.clip(np.searchsorted(t_ref, t_act) - 1, 0, len(t_ref) - 1)]
    fig, axes = plt.subplots(n, 3, figsize=(12, 2.0 * n + 1.2), sharex=True, squeeze=False,
                             gridspec_kw={'width_ratios': [1, 1, 0.8]})
    for i in range(n):
        for a in range(2):
            _draw_component(axes[i, a], (t_ref, 1e3 * (ref[:, i, a] - origin[i, a])),
                            (t_act, 1e3 * (act[:, i, a] - origin[i, a])), achieved_label,
                            min_span)
            axes[i, a].set_ylabel(f'{names[i]}  {AXES[a]}{"" if position else " rate"} [{unit}]',
                                  fontsize=8)
        _draw_error(axes[i, 2], t_act, error[:, i], free[:, i], unit,
                    0.05 if position else 1.0)
        if contact is not None and np.any(contact[:, i]):
            for ax in axes[i]:
                ax.fill_between(t_ref, 0, 1, where=contact[:, i], color='0.85', alpha=0.7, lw=0,
                                transform=ax.get_xaxis_transform(), label='touching the cube')
        for ax in axes[i]:
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=8)
    return _save_tracking(fig, axes, title, Path(path))


def _draw_component(ax, desired: tuple, achieved: tuple, achieved_label: str,
                    min_span: float) -> None:
    """One axis of one finger: the desired and the achieved (t, value) traces."""
    ax.plot(*desired, color='0.15', lw=1.6, label='desired (reference)')
    ax.plot(*achieved, color='C1', lw=1.0, ls='--', label=achieved_label)
    _span_limits(ax, np.concatenate([desired[1], achieved[1]]), min_span)


def _draw_error(ax, t: np.ndarray, error: np.ndarray, free: np.ndarray, unit: str,
                least_top: float) -> None:
    """One finger's 2-D error, scaled to its samples in free space (all of them when it is never
    free), with a note when a larger error in contact is off the scale."""
    ax.plot(t, error, color='C3', lw=0.9, label=f'|achieved − desired| (2-D) [{unit}]')
    scale = float(np.nanmax(error[free])) if free.any() else float(np.nanmax(error))
    top = max(scale * 1.25, least_top)
    ax.set_ylim(0, top)
    if np.nanmax(error) > top:
        ax.text(0.5, 0.93, f'in contact: up to {np.nanmax(error):.2g} {unit} (off scale)',
                transform=ax.transAxes, ha='center', va='top', fontsize=7, color='0.3')
    ax.set_ylabel(f'error [{unit}]', fontsize=8)


def _save_tracking(fig, axes, title: str, path: Path) -> Path:
    """The columns' titles, one legend over the figure for every trace kind, and the file."""
    n = axes.shape[0]
    axes[0, 0].set_title('X (side)', fontsize=9)
    axes[0, 1].set_title('Y (grasp)', fontsize=9)
    axes[0, 2].set_title('tracking error', fontsize=9)
    handles = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.suptitle(title, fontsize=10)
    fig.legend(list(handles.values()), list(handles), loc='upper center', ncol=len(handles),
               fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.985 - 0.25 / (2.0 * n + 1.2)))
    for ax in axes[-1]:
        ax.set_xlabel('time [s]')
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.75 / (2.0 * n + 1.2)))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_torques(t, u, path, finger_names=None, u_max=None) -> Path:
    """Figure 7: the two input torques per finger [mN·m]."""
    u = np.asarray(u)
    n = u.shape[1]
    names = finger_names or [f'finger_{i}' for i in range(n)]
    fig, axes = plt.subplots(n, 1, figsize=(10, 1.9 * n + 0.8), sharex=True, squeeze=False)
    axes = axes[:, 0]
    fig.suptitle('Torque commands of the controller (saturation limit dotted)')
    for i in range(n):
        ax = axes[i]
        ax.plot(t, 1e3 * u[:, i, 0], 'C2-', lw=1.0, label='u_ax0 (grasp axis)')
        ax.plot(t, 1e3 * u[:, i, 1], 'C3-', lw=1.0, label='u_ax1 (side axis)')
        if u_max is not None:
            for s in (-1, 1):
                ax.axhline(s * 1e3 * u_max, color='0.5', lw=0.8, ls=':')
        ax.set_ylabel(f'{names[i]} [mN·m]')
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc='upper center', ncol=len(labels), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.985 - 0.25 / (1.9 * n + 0.8)))
    axes[-1].set_xlabel('time [s]')
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.75 / (1.9 * n + 0.8)))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_loss(train_loss, val_loss, path, title='Training loss (eq. 18)') -> Path:
    """Figure 2: training and validation loss per epoch (log scale, epochs counted from 0 as the
    checkpoint's ``best_epoch``), the kept (best validation) epoch marked."""
    fig, ax = plt.subplots(figsize=(6.5, 4))
    epochs = np.arange(len(train_loss))
    ax.semilogy(epochs, train_loss, label='training (u1–u3 …)')
    ax.semilogy(epochs, val_loss, label='validation (u4)')
    best = int(np.nanargmin(val_loss))
    ax.plot(epochs[best], val_loss[best], 'ko', ms=5, label=f'kept: epoch {best} (best validation)')
    ax.set_xlabel('epoch')
    ax.set_ylabel('mean squared residual (scaled units)')
    ax.set_title(title)
    ax.grid(alpha=0.3, which='both')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_accel(t, acc_true, acc_pred, path, r2=None,
               title='Validation (u4): predicted vs true') -> Path:
    """Figure 3: predicted (dashed) vs true (solid) Ẍ, Ÿ [m/s²]."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for a, name in enumerate(('Ẍ', 'Ÿ')):
        ax = axes[a]
        ax.plot(t, acc_true[:, a], 'C0-', lw=1.0, label='true')
        ax.plot(t, acc_pred[:, a], 'C1--', lw=1.0, label='predicted')
        label = f'{name} [m/s²]' + (f'   R² = {r2[a]:.3f}' if r2 is not None else '')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc='lower right', bbox_to_anchor=(1.0, 1.0), ncol=2, fontsize=8, frameon=False)
    axes[0].set_title(title, loc='left')
    axes[1].set_xlabel('time [s]')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_sweep(rows: list[dict], path) -> Path:
    """Left: worst-finger free-space RMSE vs q_pos per noise σ (log-log, 5 % target dashed), solid
    with the torque roll-off, dotted without. Right: spectral radius of the loop around the
    frictionless linearised finger vs q_pos, with and without the roll-off."""
    fig, (ax, ax_r) = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = plt.rcParams['axes.prop_cycle'].by_key()['color']
    qs = sorted({r['q_pos'] for r in rows})
    for fc in sorted({r.get('lowpass_hz', 0.0) for r in rows}):
        style = ':' if fc == 0 else '-'
        tag = 'no roll-off' if fc == 0 else f'{fc:g} Hz roll-off'
        for c, sigma in zip(colours, sorted({r['noise_m'] for r in rows})):
            sel = sorted((r for r in rows
                          if r['noise_m'] == sigma and r.get('lowpass_hz', 0.0) == fc),
                         key=lambda r: r['q_pos'])
            ax.loglog([r['q_pos'] for r in sel], [r['worst_rmse_pct'] for r in sel], 'o' + style,
                      color=c, label=f'σ = {1e3 * sigma:g} mm, {tag}')
        radius = {r['q_pos']: r['frictionless_radius'] for r in rows
                  if r.get('lowpass_hz', 0.0) == fc}
        ax_r.semilogx(sorted(radius), [radius[q] for q in sorted(radius)], 's' + style,
                      color='tab:red', label=tag)
    ax.axhline(5.0, color='k', ls='--', lw=1, label='target 5 %')
    ax.set_xlabel('position weight q_pos [1/m²]')
    ax.set_ylabel('worst-finger RMSE [% of excursion]')
    ax.set_title('Grasp tracking vs position weight')
    ax.legend(fontsize=7)
    ax_r.axhline(1.0, color='k', ls='--', lw=1)
    ax_r.set_xlabel('position weight q_pos [1/m²]')
    ax_r.set_ylabel('spectral radius per 1 ms step')
    ax_r.set_title('Same loop around the frictionless finger')
    ax_r.legend(fontsize=8)
    for a in (ax, ax_r):
        a.grid(True, which='both', alpha=0.3)
        a.set_xticks(qs)
        a.set_xticklabels([f'{q:.2g}' for q in qs])
        a.minorticks_off()
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
