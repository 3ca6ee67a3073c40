"""Every figure: the paper's (training loss 2, predicted vs true acceleration 3, tracking 5–7), the
gain sweep, and the evaluation's comparisons of the laws and of the model against the ground truth.

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


def _grid(n_fingers: int, title: str):
    fig, axes = plt.subplots(n_fingers, 2, figsize=(10, 2.1 * n_fingers + 0.8), sharex=True,
                             squeeze=False)
    fig.suptitle(title)
    return fig, axes


def _finish(fig, axes, path: Path) -> Path:
    for ax in axes[-1]:
        ax.set_xlabel('time [s]')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_positions(t, pos, ref_pos, path, finger_names=None, contact=None) -> Path:
    """Figure 5: desired (solid) vs actual (dashed) tip position per finger and axis, in mm
    relative to the reference's starting point; shaded where the finger touches the cube."""
    pos, ref_pos = np.asarray(pos), np.asarray(ref_pos)
    n = pos.shape[1]
    names = finger_names or [f'finger_{i}' for i in range(n)]
    fig, axes = _grid(n, 'Tip position: desired (solid) vs actual (dashed)')
    origin = ref_pos[0]
    for i in range(n):
        for a in range(2):
            ax = axes[i, a]
            ax.plot(t, 1e3 * (ref_pos[:, i, a] - origin[i, a]), 'C0-', lw=1.4, label='desired')
            ax.plot(t, 1e3 * (pos[:, i, a] - origin[i, a]), 'C1--', lw=1.2, label='actual')
            if contact is not None and np.any(contact[:, i]):
                ax.fill_between(t, 0, 1, where=contact[:, i], color='0.85', alpha=0.6,
                                transform=ax.get_xaxis_transform(), label='cube contact')
            ax.set_ylabel(f'{names[i]} {AXES[a]} [mm]')
            ax.grid(alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize=8)
    return _finish(fig, axes, path)


def plot_velocities(t, vel, ref_vel, path, finger_names=None) -> Path:
    """Figure 6: desired (solid) vs actual (dashed) tip velocity per finger and axis, mm/s."""
    vel, ref_vel = np.asarray(vel), np.asarray(ref_vel)
    n = vel.shape[1]
    names = finger_names or [f'finger_{i}' for i in range(n)]
    fig, axes = _grid(n, 'Tip velocity: desired (solid) vs actual (dashed)')
    for i in range(n):
        for a in range(2):
            ax = axes[i, a]
            ax.plot(t, 1e3 * ref_vel[:, i, a], 'C0-', lw=1.4, label='desired')
            ax.plot(t, 1e3 * vel[:, i, a], 'C1--', lw=1.0, label='actual')
            ax.set_ylabel(f'{names[i]} d{AXES[a]}/dt [mm/s]')
            ax.grid(alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize=8)
    return _finish(fig, axes, path)


def plot_torques(t, u, path, finger_names=None, u_max=None) -> Path:
    """Figure 7: the two input torques per finger [mN·m]."""
    u = np.asarray(u)
    n = u.shape[1]
    names = finger_names or [f'finger_{i}' for i in range(n)]
    fig, axes = plt.subplots(n, 1, figsize=(10, 1.9 * n + 0.8), sharex=True, squeeze=False)
    axes = axes[:, 0]
    fig.suptitle('Control torques')
    for i in range(n):
        ax = axes[i]
        ax.plot(t, 1e3 * u[:, i, 0], 'C2-', lw=1.0, label='u_ax0 (grasp axis)')
        ax.plot(t, 1e3 * u[:, i, 1], 'C3-', lw=1.0, label='u_ax1 (side axis)')
        if u_max is not None:
            for s in (-1, 1):
                ax.axhline(s * 1e3 * u_max, color='0.5', lw=0.8, ls=':')
        ax.set_ylabel(f'{names[i]} [mN·m]')
        ax.grid(alpha=0.3)
    axes[0].legend(loc='best', fontsize=8)
    axes[-1].set_xlabel('time [s]')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_loss(train_loss, val_loss, path, title='Training loss (eq. 18)') -> Path:
    """Figure 2: training and validation loss per epoch (log scale)."""
    fig, ax = plt.subplots(figsize=(6.5, 4))
    epochs = np.arange(1, len(train_loss) + 1)
    ax.semilogy(epochs, train_loss, label='training (u1–u3 …)')
    ax.semilogy(epochs, val_loss, label='validation (u4)')
    ax.set_xlabel('epoch')
    ax.set_ylabel('mean squared residual (scaled units)')
    ax.set_title(title)
    ax.grid(alpha=0.3, which='both')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_accel(t, acc_true, acc_pred, path, r2=None, title='Validation (u4): predicted vs true') -> Path:
    """Figure 3: predicted (dashed) vs true (solid) Ẍ, Ÿ [m/s²]."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for a, name in enumerate(('Ẍ', 'Ÿ')):
        ax = axes[a]
        ax.plot(t, acc_true[:, a], 'C0-', lw=1.0, label='true')
        ax.plot(t, acc_pred[:, a], 'C1--', lw=1.0, label='predicted')
        label = f'{name} [m/s²]' + (f'   R² = {r2[a]:.3f}' if r2 is not None else '')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', fontsize=8)
    axes[0].set_title(title)
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
            sel = sorted((r for r in rows if r['noise_m'] == sigma and r.get('lowpass_hz', 0.0) == fc),
                         key=lambda r: r['q_pos'])
            ax.loglog([r['q_pos'] for r in sel], [r['worst_rmse_pct'] for r in sel], 'o' + style,
                      color=c, label=f'σ = {1e3 * sigma:g} mm, {tag}')
        radius = {r['q_pos']: r['frictionless_radius'] for r in rows if r.get('lowpass_hz', 0.0) == fc}
        ax_r.semilogx(sorted(radius), [radius[q] for q in sorted(radius)], 's' + style, color='tab:red',
                      label=tag)
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


def _tip_error_mm(res) -> np.ndarray:
    """(T, n) 2-D tip error of a closed-loop result [mm]."""
    return np.linalg.norm(res.pos - res.ref_pos, axis=2) * 1e3


def plot_laws(results: dict, labels: dict, trajectory: str, path) -> Path:
    """Every law of one trajectory (``results``: key → LoopResult, ``labels``: key → legend text):
    finger 0's tip Y and error, its first torque, and finger 1's error (errors on a log scale)."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.5), sharex=True)
    colours = plt.get_cmap('tab20').colors[::2] + plt.get_cmap('tab20').colors[1::2]   # 20 distinct
    for ax in axes.flat:
        ax.set_prop_cycle(color=colours[:max(len(results), 1)])
    for key, res in results.items():
        label = labels[key]
        err = _tip_error_mm(res)
        axes[0, 0].plot(res.t, (res.pos[:, 0, 1] - res.ref_pos[0, 0, 1]) * 1e3, label=label, lw=1)
        axes[0, 1].plot(res.t, err[:, 0], label=label, lw=1)
        axes[1, 0].plot(res.t, res.u[:, 0, 0], label=label, lw=0.8)
        axes[1, 1].plot(res.t, err[:, 1], label=label, lw=1)
    any_res = next(iter(results.values()))
    axes[0, 0].plot(any_res.t, (any_res.ref_pos[:, 0, 1] - any_res.ref_pos[0, 0, 1]) * 1e3, 'k--', lw=1,
                    label='reference')
    axes[0, 0].set_ylabel('finger 0 tip Y − rest [mm]')
    for ax in (axes[0, 1], axes[1, 1]):        # log: a diverging law would flatten the others
        ax.set_yscale('log')
        ax.set_ylim(1e-2, 1e2)
    axes[0, 1].set_ylabel('finger 0 error [mm]')
    axes[1, 0].set_ylabel('finger 0 u_ax0 [N·m]')
    axes[1, 1].set_ylabel('finger 1 error [mm]')
    for ax in axes[1]:
        ax.set_xlabel('time [s]')
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f'{trajectory}: every law on the same plant, reference and noise')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_feedforward(results: dict, labels: dict, trajectory: str, path, highlight: str = 'sdre_ff') -> Path:
    """A feedforward law (``highlight``, drawn thicker) against the others in ``results``: both
    grasping fingers' tip errors (log scale)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.8), sharex=True, sharey=True)
    for key, res in results.items():
        err = _tip_error_mm(res)
        for ax, i in zip(axes, (0, 2)):
            ax.plot(res.t, err[:, i], lw=1.6 if key == highlight else 0.9, label=labels[key])
    for ax, i in zip(axes, (0, 2)):
        ax.set_yscale('log')
        ax.set_ylim(1e-3, 1e1)
        ax.set_xlabel('time [s]')
        ax.set_title(f'grasping finger {i}', fontsize=9)
    axes[0].set_ylabel('tip error [mm] (in contact during the hold)')
    axes[0].legend(fontsize=7)
    fig.suptitle(f'{trajectory}: SDRE + model-inversion feedforward against the paper\'s law and the PD')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_model_vs_truth(samples: dict, path) -> Path:
    """The learned task-space acceleration against the simulator's, the exact and the projected
    one: ``samples`` holds t (T,) [s] and acc_sim, acc_exact, acc_proj, acc_learned (T, 2) [m/s²]."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(samples['t'], samples['acc_sim'][:, i], 'k', lw=1, label='simulator (measured)')
        ax.plot(samples['t'], samples['acc_exact'][:, i], lw=1, label='exact J̇q̇ + JM⁻¹(Bu − Kq − Cq̇ − g)')
        ax.plot(samples['t'], samples['acc_proj'][:, i], lw=1, label='projected on static shapes')
        ax.plot(samples['t'], samples['acc_learned'][:, i], lw=1, label='learned A(x)x + G(x)u')
        ax.set_ylabel(f'tip acceleration {"XY"[i]} [m/s²]')
    axes[0].legend(fontsize=7)
    axes[1].set_xlabel('time [s]')
    fig.suptitle('held-out signal u4: learned vs ground-truth task-space acceleration')
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
