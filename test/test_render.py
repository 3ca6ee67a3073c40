"""The rendered hand looks like the run: frames are not blank, the cube sits between the grasping
fingers' tips at mid-grasp, snapshots move, and the figures and the animation are written.

The run is real physics: the simulator's hand closes fingers 0 and 2 on the cube under a torque
ramp (no controller), recorded at 100 Hz into the arrays a bag gives
(:class:`~soft_gripper_sdre.analysis.bag.Run`); its reference is the true tip shifted 1 mm
toward the palm, so the drawn rings and dots are known apart.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
from PIL import Image
import pytest

from soft_gripper_sdre.analysis.bag import Run, Series
from soft_gripper_sdre.analysis.render import (
    GRASPING,
    HandScene,
    blank_fraction,
    replay,
    scene_joints,
    visible,
)
from soft_gripper_sdre.sim.hand import GripperSim, SimConfig
from soft_gripper_sdre.tools.judging import render as render_tool

DURATION, EVERY = 1.6, 10          # s of sim time; joint states every 10 ms
CLOSE = -0.035                     # u_ax0 [N·m] of the grasping fingers after the ramp
SHIFT = 1e-3                       # reference = true tip + 1 mm in Y


def _torque(t: float) -> np.ndarray:
    u = np.zeros((4, 2))
    u[list(GRASPING), 0] = CLOSE * min(1.0, t / 1.5)
    return u


@pytest.fixture(scope='module')
def run() -> Run:
    """A real closing motion of the hand as a Run (joint states, cube pose, tips, reference)."""
    t, q, qd, cube, tips = [], [], [], [], []
    with GripperSim(SimConfig()) as sim:
        for k in range(int(round(DURATION / 1e-3)) + 1):
            if k % EVERY == 0:
                truth = sim.truth()
                t.append(truth.t)
                q.append(truth.q)
                qd.append(truth.qd)
                cube.append(truth.cube_pose)
                tips.append(truth.tip_pos[:, :2])
            sim.step(_torque(sim.t))
    t, tips = np.array(t), np.array(tips)
    ref = np.concatenate([tips + [0.0, SHIFT], np.zeros_like(tips)], axis=2)
    zeros = Series(t, np.zeros((len(t), 4, 4)))
    return Run(tips=Series(t, tips), estimate=zeros, torques=Series(t, np.zeros((len(t), 4, 2))),
               reference=Series(t, ref), contacts=None, cube_pose=Series(t, np.array(cube)),
               joints=Series(t, np.stack([np.array(q), np.array(qd)], axis=2)),
               finger_names=('finger_0', 'finger_1', 'finger_2', 'finger_3'))


@pytest.fixture(scope='module')
def frames(run):
    with HandScene(320, 240) as scene:
        return replay(scene, run, [0.0, 0.45, DURATION])


def test_a_frame_is_not_blank(frames):
    for f in frames:
        assert f.rgb.shape == (240, 320, 3) and f.rgb.dtype == np.uint8
        assert blank_fraction(f.rgb) < 0.85                 # the hand covers a good part of it
        assert len(np.unique(f.rgb.reshape(-1, 3), axis=0)) > 50   # shaded, not flat
        assert (f.segmentation >= 0).mean() > 0.15


def test_the_cube_lies_between_the_grasping_fingers_tips(frames):
    for f in frames[1:]:
        cube = f.cube_pixels()
        assert len(cube) > 500, 'the cube is in sight'
        u0, u2 = f.tips_px[GRASPING[0], 0], f.tips_px[GRASPING[1], 0]
        lo, hi = min(u0, u2), max(u0, u2)
        centre = cube.mean(axis=0)
        assert lo < centre[0] < hi
        # the cube's projected centre is where the renderer drew the cube
        assert np.abs(centre - f.cube_px).max() < 15
        # and the tips are at the cube's height in the image, one each side of it
        assert cube[:, 1].min() - 40 < f.tips_px[GRASPING[0], 1] < cube[:, 1].max() + 40
    # closing brings the tips toward the cube in the image
    gap = [abs(f.tips_px[GRASPING[1], 0] - f.tips_px[GRASPING[0], 0]) for f in frames]
    assert gap[-1] < gap[0] - 10


def test_projected_tips_are_on_the_drawn_fingers(run, frames):
    with HandScene(320, 240) as scene:
        for f in frames:
            seen = visible(f, scene, range(4))
            assert seen[list(GRASPING)].all()


def test_snapshots_differ(frames):
    a, b, c = (f.rgb.astype(int) for f in frames)
    assert np.abs(a - b).mean() > 0.5 and np.abs(b - c).mean() > 0.5
    assert (np.abs(a - c).sum(axis=2) > 30).mean() > 0.01       # whole fingers moved


def test_reference_and_tip_are_drawn_apart_by_the_shift(run, frames):
    for f in frames:
        np.testing.assert_allclose(f.errors_mm, 1e3 * SHIFT, rtol=1e-6)
        # the grasping fingers move across the image (1 mm is about 1.2 px at 320 x 240)
        apart = np.linalg.norm(f.refs_px - f.tips_px, axis=1)[list(GRASPING)]
        assert np.all(apart > 0.8)


def test_hand_fingers_must_fit_the_run(run):
    with pytest.raises(ValueError, match='do not fit'):
        scene_joints(run, (0, 1, 2))
    with pytest.raises(ValueError, match='do not fit'):
        scene_joints(run, (0, 1, 2, 2))


def test_render_run_writes_the_figures_and_the_animation(run, tmp_path):
    result = render_tool.render_run('in-process run', tmp_path, instants=(0.5, 1.0, 1.5),
                                    fps=10.0, gif_width=160, run=run)
    assert result['files'] == [render_tool.FIG1, render_tool.FIG4, render_tool.GIF]
    for name in (render_tool.FIG1, render_tool.FIG4):
        img = np.asarray(Image.open(tmp_path / name).convert('RGB'))
        assert blank_fraction(img) < 0.9
    gif = Image.open(tmp_path / render_tool.GIF)
    assert gif.n_frames == result['frames'] == int(DURATION * 10) + 1
    first = np.asarray(gif.convert('RGB')).astype(int)
    gif.seek(gif.n_frames - 1)
    last = np.asarray(gif.convert('RGB')).astype(int)
    assert np.abs(first - last).mean() > 0.5
    with pytest.raises(ValueError, match='outside the run'):
        render_tool.render_run('in-process run', tmp_path, instants=(2.5,), run=run)


def test_default_instants_are_the_papers_within_the_run():
    assert render_tool.default_instants(0.0, 6.0) == render_tool.PAPER_INSTANTS
    assert render_tool.default_instants(0.0, 1.8) == (1.5, 1.75)
    assert render_tool.default_instants(0.0, 1.0) == (0.2, 0.4, 0.6, 0.8)   # a short run


@pytest.mark.parametrize('args, message', [
    (['/nonexistent/bag', '--out', 'x'], 'does not exist'),
    (['b', '--out', 'x', '--fps', '0'], '--fps'),
    (['b', '--out', 'x', '--gif-width', '10'], '--gif-width'),
    (['b', '--out', 'x', '--hand-fingers', 'a,b'], 'hand fingers'),
])
def test_cli_refuses_bad_input(args, message, tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'soft_gripper_sdre.tools.judging.render', *args],
                          capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert 'Traceback' not in proc.stderr
