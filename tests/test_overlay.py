"""The frame overlay: projection onto the rendered image, what it draws, and the streaming video writer."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import vafn_gym  # noqa: F401
from vafn_gym.overlay import FrameOverlay, VideoWriter, arm_rgb, mp4_available, project


@pytest.fixture()
def env() -> gym.Env:
    env = gym.make("VAFN/ThreeArmReach-v1", render_mode="rgb_array", instruction="2,3,1", render_width=320,
                   render_height=240)
    env.reset(seed=0)
    yield env
    env.close()


def test_projection_lands_on_the_rendered_target_markers(env: gym.Env) -> None:
    base = env.unwrapped
    frame = env.render().astype(int)
    for arm in (1, 2, 3):
        (x, y), visible = (v[0] for v in project(base.task.current_target(arm), base.camera(), 320, 240))
        assert visible
        patch = frame[int(y) - 2:int(y) + 3, int(x) - 2:int(x) + 3].reshape(-1, 3)
        channel = int(np.argmax(arm_rgb(base.layout, arm)))  # arm 1 red, 2 green, 3 blue
        others = [c for c in range(3) if c != channel]
        assert np.any(patch[:, channel] > patch[:, others].max(axis=1) + 40), f"arm {arm}'s marker not at ({x}, {y})"


def test_overlay_draws_banners_and_highlights_the_current_waypoint(env: gym.Env) -> None:
    overlay = FrameOverlay(env)
    frame = env.render()
    first = overlay(frame, step=0)
    assert first.shape == frame.shape and first.dtype == np.uint8
    assert np.array_equal(frame, env.render()), "the input frame is not modified"
    assert np.abs(first[:20].astype(int) - frame[:20]).mean() > 30, "no instruction banner"
    env.unwrapped.task.waypoint_index = 1  # test-only: pretend waypoint 1 was reached
    second = overlay(frame, step=0)
    assert np.abs(second[:12].astype(int) - first[:12]).sum() > 0, "the highlighted waypoint did not move"
    contact = overlay(frame, info={"collision": True}, step=0)
    assert np.abs(contact[-12:].astype(int) - first[-12:]).sum() > 0, "the collision state is not shown"
    with pytest.raises(ValueError, match="uint8"):
        overlay(frame.astype(float))
    with pytest.raises(TypeError, match="MultiArmEnv"):
        FrameOverlay(gym.make("CartPole-v1"))


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_video_writer_streams_frames(tmp_path: Path, suffix: str) -> None:
    if suffix == ".mp4" and not mp4_available():
        pytest.skip("imageio-ffmpeg not installed")
    frames = [np.full((31, 41, 3), 20 * i, np.uint8) for i in range(5)]
    with VideoWriter(tmp_path / f"v{suffix}", fps=12) as writer:
        for frame in frames:
            writer.append(frame)
        with pytest.raises(ValueError, match="shape"):
            writer.append(np.zeros((8, 8, 3), np.uint8))
    assert writer.n_frames == 5 and (tmp_path / f"v{suffix}").stat().st_size > 0
    import imageio.v2 as imageio

    read = imageio.mimread(tmp_path / f"v{suffix}")
    assert len(read) == 5 and abs(int(np.asarray(read[-1])[..., :3].mean()) - 80) <= 3
    with pytest.raises(ValueError, match="must end in"):
        VideoWriter(tmp_path / "v.avi", fps=12)
