"""Labelled frames and video files: the one overlay every recorder draws on ``render()`` frames.

:class:`FrameOverlay` reads the env's state (read-only) and draws, on a copy of an ``rgb_array`` frame:

- a top banner with the instruction, one box per waypoint: reached ones dimmed, the current one filled with the
  active arm's colour, pending ones outlined; below it the active arm's number and colour (or "holding");
- each arm's label (``arm k`` in its colour) at its base, the active arm's outlined;
- each pending target as a ring in its arm's colour (large enough to see at any frame size) with a line from the
  active arm's end effector to its target;
- a bottom banner with the step counter and the success / collision state, plus any caller notes.

:class:`VideoWriter` streams frames to an ``.mp4`` (imageio-ffmpeg) or a ``.gif`` (Pillow, palettised frames) so a
recorder never holds full RGB frames in memory.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from vafn_gym.sim.bullet import pybullet

#: Vertical field of view, near and far planes of the render camera (as in :meth:`vafn_gym.sim.BulletSim.render`).
CAMERA_FOV = 60.0
CAMERA_NEAR = 0.05
CAMERA_FAR = 10.0
VIDEO_SUFFIXES = (".gif", ".mp4")
#: Arm labels stand at this multiple of the base's distance from the table centre; target labels this far (metres)
#: from their target, toward the arm.
LABEL_RADIUS_FACTOR = 1.3
TARGET_LABEL_OFFSET = 0.09
BANNER_ALPHA = 170
WHITE = (255, 255, 255)
GREY = (150, 150, 150)
RED = (235, 50, 50)
GREEN = (60, 200, 80)
YELLOW = (255, 215, 0)


@functools.lru_cache(maxsize=32)
def _font(size: int, bold: bool = False) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    """DejaVu Sans (shipped with matplotlib) at ``size`` px, or Pillow's default font."""
    try:
        import matplotlib

        name = "DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf"
        return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / name), size)
    except (ImportError, OSError):
        return ImageFont.load_default(size)


def arm_rgb(layout: Any, arm: int) -> tuple[int, int, int]:
    """``arm``'s colour as 0-255 RGB (the layout's marker colour)."""
    red, green, blue, _ = layout.colour(arm)
    return int(255 * red), int(255 * green), int(255 * blue)


def project(points: np.ndarray, camera: Mapping[str, Any], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(N, 2)`` of world ``points`` ``(N, 3)`` seen by ``camera``, and which lie in front of it."""
    view = np.array(pybullet().computeViewMatrixFromYawPitchRoll(
        [float(x) for x in camera["target"]], float(camera["distance"]), float(camera["yaw"]), float(camera["pitch"]),
        0.0, 2,
    )).reshape(4, 4).T
    proj = pybullet().computeProjectionMatrixFOV(CAMERA_FOV, width / height, CAMERA_NEAR, CAMERA_FAR)
    proj = np.array(proj).reshape(4, 4).T
    points = np.atleast_2d(np.asarray(points, dtype=float))
    clip = (proj @ view @ np.c_[points, np.ones(len(points))].T).T
    w = clip[:, 3]
    ndc = clip[:, :2] / np.where(np.abs(w) < 1e-9, 1e-9, w)[:, None]
    pixels = np.c_[(ndc[:, 0] + 1.0) * 0.5 * width, (1.0 - ndc[:, 1]) * 0.5 * height]
    return pixels, w > 0


class FrameOverlay:
    """Draws the instruction, arm labels, targets, state and step counter on frames of one vafn env.

    :param env: a (possibly wrapped) :class:`~vafn_gym.envs.MultiArmEnv` or stream env; only read.
    """

    def __init__(self, env: Any) -> None:
        base = env.unwrapped
        if not hasattr(base, "task") or not hasattr(base, "layout"):
            raise TypeError(f"FrameOverlay needs a vafn_gym MultiArmEnv, got {type(base).__name__}")
        self.env = base

    def __call__(self, frame: np.ndarray, info: Mapping[str, Any] | None = None, step: int | None = None,
                 notes: Sequence[str] = ()) -> np.ndarray:
        """A labelled copy of ``frame`` (H, W, 3 uint8) for the env's current state.

        :param frame: the env's ``render()`` output.
        :param info: the last ``info`` dict (its ``collision`` flag marks a contact on this step).
        :param step: the step counter shown (default: the stream's total steps or the episode's steps).
        :param notes: extra lines for the bottom banner (e.g. where the instruction came from).
        """
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"frame must be an (H, W, 3) uint8 array, got {frame.shape} {frame.dtype}")
        height, width = frame.shape[:2]
        image = Image.fromarray(frame).convert("RGBA")
        layer = Image.new("RGBA", image.size, (0, 0, 0, 0))
        draw = ImageDraw.Draw(layer)
        size = max(9, height // 22)
        font, bold = _font(size), _font(size, bold=True)
        self._draw_scene(draw, width, height, size, bold)
        self._draw_banner(draw, width, size, font, bold)
        self._draw_status(draw, width, height, size, font, bold, info, step, notes)
        return np.asarray(Image.alpha_composite(image, layer).convert("RGB"))

    # --- pieces ---
    def _draw_scene(self, draw: ImageDraw.ImageDraw, width: int, height: int, size: int, bold: Any) -> None:
        env, task = self.env, self.env.task
        camera = env.camera()
        arms = env.layout.arm_ids
        active = task.active_arm
        pending = set(task.instruction.remaining_arms(task.waypoint_index)) if active is not None else set()
        # Labels stand just outside each base (beyond the table edge), so the far arm's label clears the centre.
        outside = np.array([env.layout.base_position(a) * LABEL_RADIUS_FACTOR for a in arms])
        bases, _ = project(outside, camera, width, height)
        for arm, (x, y) in zip(arms, bases):
            text = f"arm {arm}"
            box = draw.textbbox((0, 0), text, font=bold)
            w, h = box[2] - box[0], box[3] - box[1]
            # Near arms: label below the point; far arms (upper half): above it, clear of the targets at the centre.
            left, top = x - w / 2 - 3, (min(y + 4, height - h - 8) if y > height / 2 else max(y - h - 10, 0))
            draw.rounded_rectangle((left, top, left + w + 6, top + h + 6), radius=3,
                                   fill=(*arm_rgb(env.layout, arm), 230), outline=YELLOW if arm == active else None,
                                   width=max(1, size // 6))
            draw.text((left + 3 - box[0], top + 3 - box[1]), text, font=bold, fill=WHITE)
        ring = max(6, height // 30)
        for arm in arms:
            if arm not in pending:
                continue
            (x, y), visible = (v[0] for v in project(task.current_target(arm), camera, width, height))
            if not visible:
                continue
            colour = arm_rgb(env.layout, arm)
            if arm == active:
                (ex, ey), _ = (v[0] for v in project(env.arms[arm].ee_position, camera, width, height))
                draw.line((ex, ey, x, y), fill=(*colour, 220), width=max(1, size // 7))
            thick = max(2, size // 4) if arm == active else max(1, size // 8)
            draw.ellipse((x - ring, y - ring, x + ring, y + ring), outline=(*colour, 255), width=thick)
            draw.ellipse((x - 2, y - 2, x + 2, y + 2), fill=(*colour, 255))
            # The label sits on the side of the target that faces its own arm, so clustered targets stay readable.
            toward = env.layout.base_position(arm) - task.current_target(arm)
            toward[2] = 0.0
            anchor = task.current_target(arm) + TARGET_LABEL_OFFSET * toward / max(np.linalg.norm(toward), 1e-9)
            (lx, ly), _ = (v[0] for v in project(anchor, camera, width, height))
            box = draw.textbbox((0, 0), f"T{arm}", font=bold)
            draw.text((lx - (box[2] + box[0]) / 2, ly - (box[3] + box[1]) / 2), f"T{arm}", font=bold,
                      fill=(*colour, 255), stroke_width=1, stroke_fill=(0, 0, 0, 255))

    def _draw_banner(self, draw: ImageDraw.ImageDraw, width: int, size: int, font: Any, bold: Any) -> None:
        env, task = self.env, self.env.task
        pad = max(2, size // 4)
        draw.rectangle((0, 0, width, 2 * size + 4 * pad), fill=(0, 0, 0, BANNER_ALPHA))
        x = pad
        draw.text((x, pad), "instruction", font=font, fill=WHITE)
        x += draw.textlength("instruction ", font=font)
        if not len(task.instruction):
            draw.text((x, pad), "(none: holding)", font=font, fill=GREY)
        for index, waypoint in enumerate(task.instruction):
            text = str(waypoint.arm)
            w = draw.textlength(text, font=bold) + 2 * pad
            box = (x, pad, x + w, pad + size + pad)
            if index < task.waypoint_index:
                draw.rectangle(box, outline=GREY, width=1)
                draw.text((x + pad, pad), text, font=bold, fill=GREY)
            elif index == task.waypoint_index:
                draw.rectangle(box, fill=(*arm_rgb(env.layout, waypoint.arm), 255), outline=YELLOW, width=2)
                draw.text((x + pad, pad), text, font=bold, fill=WHITE)
            else:
                draw.rectangle(box, outline=WHITE, width=1)
                draw.text((x + pad, pad), text, font=bold, fill=WHITE)
            x += w + pad
            if x > width - 2 * size:
                break
        y = 2 * pad + size + pad
        active = task.active_arm
        if active is None:
            label = "active: none (holding)" if not len(task.instruction) else "active: none (instruction done)"
            draw.text((pad, y), label, font=font, fill=GREY)
        else:
            text = f"active: arm {active}"
            draw.text((pad, y), text, font=bold, fill=WHITE)
            cx = pad + draw.textlength(text + " ", font=bold)
            draw.ellipse((cx, y + 1, cx + size - 2, y + size - 1), fill=(*arm_rgb(env.layout, active), 255),
                         outline=WHITE)

    def _draw_status(self, draw: ImageDraw.ImageDraw, width: int, height: int, size: int, font: Any, bold: Any,
                     info: Mapping[str, Any] | None, step: int | None, notes: Sequence[str]) -> None:
        env, task = self.env, self.env.task
        pad = max(2, size // 4)
        lines = [str(note) for note in notes]
        top = height - (len(lines) + 1) * (size + pad) - pad
        draw.rectangle((0, top, width, height), fill=(0, 0, 0, BANNER_ALPHA))
        for index, line in enumerate(lines):
            draw.text((pad, top + pad + index * (size + pad)), line, font=font, fill=WHITE)
        y = height - size - pad - 1
        if step is None:
            step = getattr(env, "total_steps", task.steps)
        draw.text((pad, y), f"step {step}", font=font, fill=WHITE)
        contact_now = bool(info.get("collision", False)) if info is not None else False
        if contact_now:
            state, colour = "COLLISION", RED
        elif task.collided:
            state, colour = "collided earlier", RED
        elif len(task.instruction) and task.complete:
            state, colour = "SUCCESS", GREEN
        elif len(task.instruction):
            current = min(task.waypoint_index + 1, len(task.instruction))
            state, colour = f"waypoint {current}/{len(task.instruction)}", WHITE
        else:
            state, colour = "no collision", WHITE
        text_width = draw.textlength(state, font=bold)
        draw.text((width - text_width - pad, y), state, font=bold, fill=colour)


def even_frame(frame: np.ndarray) -> np.ndarray:
    """``frame`` padded by edge pixels to even height and width (H.264 in yuv420p needs them)."""
    pad_h, pad_w = frame.shape[0] % 2, frame.shape[1] % 2
    return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge") if pad_h or pad_w else frame


class VideoWriter:
    """Streams RGB frames to ``path`` (``.mp4`` through imageio-ffmpeg, ``.gif`` through Pillow).

    MP4 frames go straight to the encoder; GIF frames are palettised on arrival (1 byte per pixel) and written on
    :meth:`close`, so memory stays a third of holding the RGB frames.

    :param path: output file, ending in ``.mp4`` or ``.gif``.
    :param fps: frames per second.
    """

    def __init__(self, path: str | Path, fps: float) -> None:
        self.path = Path(path)
        if self.path.suffix not in VIDEO_SUFFIXES:
            raise ValueError(f"video path must end in one of {VIDEO_SUFFIXES}, got {self.path}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.fps = float(fps)
        self.n_frames = 0
        self._gif: list[Image.Image] = []
        self._writer: Any = None
        self._shape: tuple[int, ...] | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.suffix == ".mp4":
            if not mp4_available():
                raise RuntimeError(f"writing {self.path} needs imageio and imageio-ffmpeg "
                                   "(pip install imageio imageio-ffmpeg); or give a .gif path")
            import imageio.v2 as imageio

            self._writer = imageio.get_writer(self.path, fps=self.fps, codec="libx264", macro_block_size=1,
                                              quality=7, ffmpeg_log_level="error")

    def append(self, frame: np.ndarray) -> None:
        """Add one (H, W, 3) uint8 frame; every frame must have the first one's size."""
        frame = np.asarray(frame)
        if self._shape is None:
            self._shape = frame.shape
        elif frame.shape != self._shape:
            raise ValueError(f"frame {self.n_frames} has shape {frame.shape}, the first had {self._shape}")
        if self._writer is not None:
            self._writer.append_data(even_frame(frame))
        else:
            self._gif.append(Image.fromarray(frame).quantize(colors=255, method=Image.Quantize.MEDIANCUT))
        self.n_frames += 1

    def close(self) -> Path:
        """Finish the file and return its path (``ValueError`` when no frame was added)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        elif self._gif:
            duration = max(20, int(round(1000.0 / self.fps / 10.0)) * 10)  # GIF delays are in 10 ms units
            self._gif[0].save(self.path, save_all=True, append_images=self._gif[1:], duration=duration, loop=0)
            self._gif = []
        if self.n_frames == 0:
            raise ValueError(f"no frames were recorded for {self.path}")
        return self.path

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._writer is not None or self._gif:
            self.close()


def mp4_available() -> bool:
    """Whether imageio and imageio-ffmpeg can write MP4 files here."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return False
    return True


def frame_rate(env: Any, frame_skip: int = 1) -> float:
    """Frames per second of a recording that keeps every ``frame_skip``-th control step (real-time playback)."""
    return max(1.0, float(env.unwrapped.metadata.get("render_fps", 30)) / max(frame_skip, 1))


__all__ = ["FrameOverlay", "VideoWriter", "arm_rgb", "even_frame", "frame_rate", "mp4_available",
           "project"]
