"""The paper's Figs. 1 and 4 and an animation of the grasp, drawn from a recorded run.

    python -m soft_gripper_sdre.tools.judging.render BAG --out DIR [--instants 1.5 1.75 2 2.75]
        [--no-gif] [--fps 12] [--gif-width 400] [--hand-fingers 0,2]

Replays the run's ``joint_states`` and ``cube_pose`` in the simulator's own hand, rendered by
PyBullet's CPU renderer (no display, no GPU: :mod:`soft_gripper_sdre.analysis.render`), and
writes to DIR:

* ``fig1_hand.png``: the hand at rest (the run's first joint state), each finger's controlled
  point (link 9's centre of mass) marked;
* ``fig4_snapshots.png``: snapshots at ``--instants`` (default the paper's 1.5, 1.75 and 2 s, and
  2.75 s with the cube held, those within the run; four spread over a shorter run), the reference
  (ring) and the true tip (dot) of every finger drawn in, the grasping fingers' reference paths;
* ``grasp.gif``: the whole run at ``--fps`` frames per second of sim time, the same overlay.

Exit status 2 for a missing or unusable bag or bad arguments.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np

from soft_gripper_sdre.analysis.bag import BagError, extract_run
from soft_gripper_sdre.analysis.render import GRASPING, HandScene, reference_paths, replay, visible

FIG1 = 'fig1_hand.png'
FIG4 = 'fig4_snapshots.png'
GIF = 'grasp.gif'
#: the paper's Fig. 4 shows the grasp between 1.5 and 2 s; 2.75 s is the hold, the cube squeezed
PAPER_INSTANTS = (1.5, 1.75, 2.0, 2.75)
REF_COLOUR = (0.85, 0.1, 0.1)
TIP_COLOUR = (0.0, 0.0, 0.0)


def _crop(frames, margin: int = 8) -> tuple[slice, slice]:
    """Rows and columns that hold something other than background in any frame, plus a margin."""
    mask = np.zeros(frames[0].segmentation.shape, dtype=bool)
    for f in frames:
        mask |= f.segmentation >= 0
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return slice(None), slice(None)
    h, w = mask.shape
    return (slice(max(0, rows[0] - margin), min(h, rows[-1] + margin + 1)),
            slice(max(0, cols[0] - margin), min(w, cols[-1] + margin + 1)))


def _draw_overlay(ax, frame, names, paths=None, labels=False, legend=False) -> None:
    """The reference (ring) and the true tip (dot) of each finger on ``ax`` (pixel coordinates)."""
    if paths is not None:
        for i in range(paths.shape[1]):
            ax.plot(paths[:, i, 0], paths[:, i, 1], color=REF_COLOUR, lw=0.8, alpha=0.6,
                    label='reference path' if legend and i == 0 else None)
    ax.scatter(frame.refs_px[:, 0], frame.refs_px[:, 1], s=70, facecolors='none',
               edgecolors=[REF_COLOUR], linewidths=1.3, label='reference' if legend else None,
               zorder=3)
    ax.scatter(frame.tips_px[:, 0], frame.tips_px[:, 1], s=9, color=TIP_COLOUR,
               label='true tip (link 9 centre of mass)' if legend else None, zorder=4)
    if labels:
        for (u, v), name in zip(frame.tips_px, names):
            ax.annotate(name, (u, v), xytext=(6, -10), textcoords='offset points', fontsize=8)


def figure1(frame, names, hidden, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.2, 4.2), dpi=110)
    ax.imshow(frame.rgb)
    ax.scatter(frame.tips_px[:, 0], frame.tips_px[:, 1], s=40, color='#ffcc00', edgecolors='k',
               linewidths=0.8, zorder=4, label='controlled point (link 9 centre of mass)')
    for (u, v), name, behind in zip(frame.tips_px, names, hidden):
        ax.annotate(name + (' (behind the cube)' if behind else ''), (u, v), xytext=(8, -12),
                    textcoords='offset points', fontsize=8,
                    bbox=dict(boxstyle='round,pad=0.15', fc='white', ec='none', alpha=0.8))
    ax.set_axis_off()
    ax.legend(loc='lower center', fontsize=7, frameon=False, bbox_to_anchor=(0.5, -0.06))
    ax.set_title('Fig. 1  The four-finger soft gripper at rest, the cube on the palm', fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def figure4(frames, names, paths, grasping, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    rows, cols = _crop(frames)
    fig, axes = plt.subplots(1, len(frames), figsize=(2.6 * len(frames), 3.3), dpi=110,
                             squeeze=False)
    for k, (ax, frame) in enumerate(zip(axes[0], frames)):
        h, w = frame.rgb.shape[:2]
        ax.imshow(frame.rgb, extent=(-0.5, w - 0.5, h - 0.5, -0.5))
        _draw_overlay(ax, frame, names, paths[:, list(grasping)], legend=k == 0)
        ax.set_xlim(cols.start - 0.5, cols.stop - 0.5)
        ax.set_ylim(rows.stop - 0.5, rows.start - 0.5)
        ax.set_axis_off()
        err = ', '.join(f'{frame.errors_mm[i]:.2f}' for i in grasping)
        ax.set_title(f't = {frame.t:.2f} s\nerror {err} mm', fontsize=8)
    fig.legend(loc='lower center', ncol=3, fontsize=7, frameon=False)
    fig.suptitle('Fig. 4  Snapshots of the cube grasp: reference (ring) and true tip (dot); '
                 'error of the grasping fingers', fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.93))
    fig.savefig(path)
    plt.close(fig)


def animation(frames, path: Path, fps: float) -> None:
    """An endlessly looping GIF of ``frames`` with the overlay drawn by Pillow."""
    from PIL import Image, ImageDraw
    rows, cols = _crop(frames)
    images = []
    for frame in frames:
        img = Image.fromarray(frame.rgb[rows, cols])
        draw = ImageDraw.Draw(img)
        off = np.array([cols.start or 0, rows.start or 0])
        for u, v in frame.refs_px - off:
            if np.isfinite(u) and np.isfinite(v):
                draw.ellipse((u - 5, v - 5, u + 5, v + 5), outline=(215, 25, 25), width=2)
        for u, v in frame.tips_px - off:
            draw.ellipse((u - 2, v - 2, u + 2, v + 2), fill=(0, 0, 0))
        draw.text((4, 4), f't = {frame.t:4.2f} s', fill=(0, 0, 0))
        images.append(img.convert('P', palette=Image.Palette.ADAPTIVE, colors=64))
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)),
                   loop=0, optimize=True)


def default_instants(t0: float, t_end: float) -> tuple[float, ...]:
    """:data:`PAPER_INSTANTS` that fall within the run [t0, t_end]; if fewer than two do (a short
    run), four instants spread over it."""
    inside = tuple(t for t in PAPER_INSTANTS if t0 <= t <= t_end)
    if len(inside) >= 2:
        return inside
    return tuple(float(t) for t in np.round(np.linspace(t0, t_end, 6)[1:-1], 3))


def render_run(bag: str | Path, out: str | Path, instants=None, gif: bool = True,
               fps: float = 12.0, gif_width: int = 400, hand_fingers=None, run=None) -> dict:
    """Write :data:`FIG1`, :data:`FIG4` and (``gif``) :data:`GIF` of the run in ``bag`` to ``out``.

    Args:
        instants: sim times of the Fig. 4 snapshots [s]; None: :func:`default_instants`.
        run: the bag already read by :func:`~soft_gripper_sdre.analysis.bag.extract_run`
            (read here if None).

    Returns:
        What was written and how long it took: ``{'files': [...], 'wall_s': ..., 'frames': ...}``.

    Raises:
        BagError: the bag is missing, unreadable or has no joint_states.
        ValueError: ``instants`` outside the run, or ``hand_fingers`` that do not fit it.
    """
    t0 = time.monotonic()
    run = extract_run(bag) if run is None else run
    if run.joints is None:
        raise BagError(f'bag {bag}: no joint_states, so the hand cannot be posed')
    t_end = float(run.joints.t[-1])
    if instants is None:
        instants = default_instants(float(run.joints.t[0]), t_end)
    bad = [t for t in instants if not run.joints.t[0] <= t <= t_end]
    if bad:
        raise ValueError(f'instants {bad} lie outside the run ({run.joints.t[0]:.2f} to '
                         f'{t_end:.2f} s)')
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = list(run.finger_names)
    n = run.joints.values.shape[1]
    if hand_fingers is None:
        hand_fingers = GRASPING if n == 2 else tuple(range(n))
    grasping = [i for i, hf in enumerate(hand_fingers) if hf in GRASPING]
    written = []
    with HandScene(480, 360) as scene:
        paths = reference_paths(scene, run, hand_fingers)
        rest = replay(scene, run, [float(run.joints.t[0])], hand_fingers)[0]
        figure1(rest, names, ~visible(rest, scene, hand_fingers), out / FIG1)
        snaps = replay(scene, run, instants, hand_fingers)
        figure4(snaps, names, paths, grasping, out / FIG4)
        written += [FIG1, FIG4]
    n_frames = 0
    if gif:
        height = int(round(gif_width * 0.75))
        with HandScene(gif_width, height) as scene:
            times = np.arange(float(run.joints.t[0]), t_end + 1e-9, 1.0 / fps)
            frames = replay(scene, run, times, hand_fingers)
            animation(frames, out / GIF, fps)
            n_frames = len(frames)
        written.append(GIF)
    return {'files': written, 'frames': n_frames, 'wall_s': round(time.monotonic() - t0, 2)}


def _hand_fingers(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a comma-separated list of hand fingers '
                                         '0-3') from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.judging.render',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory of a run (with joint_states)')
    parser.add_argument('--out', required=True, type=Path, help='output directory')
    parser.add_argument('--instants', type=float, nargs='+', default=None, metavar='S',
                        help='sim times of the Fig. 4 snapshots [s] (default '
                             f'{" ".join(map(str, PAPER_INSTANTS))}, those within the run)')
    parser.add_argument('--no-gif', action='store_true', help=f'do not write {GIF}')
    parser.add_argument('--fps', type=float, default=12.0,
                        help='animation frames per second of sim time (default %(default)s)')
    parser.add_argument('--gif-width', type=int, default=400,
                        help='rendered width of the animation [px] (default %(default)s)')
    parser.add_argument('--hand-fingers', type=_hand_fingers, default=None, metavar='I,J,...',
                        help="which hand finger (0-3) each of the bag's fingers is "
                             '(default 0,1,2,3 for four fingers, 0,2 for two)')
    args = parser.parse_args(argv)
    if not 1.0 <= args.fps <= 50.0:
        parser.error(f'--fps must be in [1, 50], got {args.fps:g}')
    if not 64 <= args.gif_width <= 1280:
        parser.error(f'--gif-width must be in [64, 1280] px, got {args.gif_width}')
    if args.instants is not None and len(args.instants) > 8:
        parser.error('--instants takes 1 to 8 times')
    try:
        instants = None if args.instants is None else tuple(args.instants)
        result = render_run(args.bag, args.out, instants, not args.no_gif, args.fps,
                            args.gif_width, args.hand_fingers)
    except (BagError, ValueError) as exc:
        print(f'{parser.prog}: error: {exc}', file=sys.stderr)
        return 2
    except OSError as exc:
        print(f'{parser.prog}: error: cannot write to {args.out}: {exc}', file=sys.stderr)
        return 2
    print(f'wrote {", ".join(result["files"])} to {args.out} in {result["wall_s"]:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
