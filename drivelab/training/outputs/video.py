"""Videos of evaluation episodes: what people look at first.

:class:`Recorder` films the episodes that env 0 of a vector env plays during
:func:`drivelab.training.collection.evaluation.run_episodes`, from the env's ``render()`` in ``rgb_array`` mode
(MetaDrive: its pygame top-down view, no 3D assets; Duckietown: its camera; any Gymnasium env:
its own rgb_array). An overlay (step, speed, return so far, cross-track error where the env
reports it, the action) makes the video explain itself. Files are written with imageio: MP4
through imageio-ffmpeg's bundled ffmpeg, GIF when the name ends in .gif.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import imageio.v2 as imageio
import numpy as np

from drivelab.config import check_output_path
from drivelab.errors import DrivelabError

# What a video file may be called: MP4 (H.264 through ffmpeg) or an animated GIF.
VIDEO_SUFFIXES = (".mp4", ".gif")


def overlay(frame: np.ndarray, lines: list[str]) -> np.ndarray:
    """``lines`` of white text on a dark band at the top-left of an (H, W, 3) uint8 frame."""
    out = np.ascontiguousarray(frame[..., :3], dtype=np.uint8).copy()
    scale = max(0.35, out.shape[1] / 1000)
    height = int(22 * scale / 0.5)
    width = min(out.shape[1], int(max(len(line) for line in lines) * 10 * scale / 0.5) + 10)
    out[: height * len(lines) + 6, :width] //= 3
    for i, line in enumerate(lines):
        cv2.putText(out, line, (5, (i + 1) * height), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _value(info: dict, key: str) -> float | None:
    if key not in info or not info.get(f"_{key}", np.ones(1, bool))[0]:
        return None
    return float(np.asarray(info[key])[0])


def check_video_path(path: Path, per_episode: bool = False) -> None:
    """The video file (or with ``per_episode`` the directory of one file per episode) can be
    written, with a name that says MP4 or GIF: one line before the episodes are played, not a
    traceback after them."""
    if per_episode:
        check_output_path(path, "--video-dir", directory=True)
        return
    check_output_path(path, "--video")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise DrivelabError(f"--video: {path} must end in {' or '.join(VIDEO_SUFFIXES)}, the formats drivelab writes")


class Recorder:
    """Films env 0's episodes: into one file (``path`` ends in .mp4 or .gif) or, with
    ``per_episode``, into ``path/episode_<k>.mp4``, k being the evaluation episode index.

    The envs must be built with ``render_mode="rgb_array"``; use one env, since ``render`` is
    called on every env of the vector env."""

    def __init__(self, path: str | Path, per_episode: bool = False, with_overlay: bool = True, fps: int = 10,
                 max_episodes: int | None = None, thumbnails: int = 0):
        self.path, self.per_episode, self.with_overlay, self.fps = Path(path), per_episode, with_overlay, fps
        self.max_episodes = max_episodes
        self.thumbnails: list[np.ndarray] = []      # every 10th frame, at most `thumbnails` of them
        self._keep = thumbnails
        self.paths: list[Path] = []
        self.frames = 0
        self._writer = None
        self._episode, self._t, self._return = 0, 0, 0.0
        check_video_path(self.path, per_episode)
        (self.path if per_episode else self.path.parent).mkdir(parents=True, exist_ok=True)

    def _recording(self) -> bool:
        return self.max_episodes is None or self._episode < self.max_episodes

    def start(self, envs, info: dict, episode: int) -> None:
        """After env 0 was reset into evaluation episode ``episode``."""
        self._episode, self._t, self._return = int(episode), 0, 0.0
        if not self._recording():
            return
        if self.per_episode or self._writer is None:
            # one frame per step of `envs`; an env that holds each action for N steps (env.action_repeat)
            # shows every N-th frame, so the video plays at fps / N to keep real time
            repeat = int(getattr(envs, "metadata", {}).get("action_repeat", 1))
            self._open(self.path / f"episode_{episode:03d}.mp4" if self.per_episode else self.path, self.fps / repeat)
        self._frame(envs, info, None)

    def step(self, envs, action: np.ndarray, reward: float, info: dict, done: bool) -> None:
        """After a step of the vector env (``action``, ``reward``: env 0's)."""
        self._t += 1
        self._return += float(reward)
        if self._recording():
            self._frame(envs, info, action)
            if done and self.per_episode:
                self._close_writer()

    def _frame(self, envs, info: dict, action) -> None:
        frame = np.asarray(envs.call("render")[0], dtype=np.uint8)
        if self.with_overlay:
            lines = [f"episode {self._episode}  step {self._t}  return {self._return:.1f}"]
            speed, cte = _value(info, "speed"), _value(info, "cte")
            if speed is not None:
                lines.append(f"speed {3.6 * speed:.0f} km/h" + (f"  CTE {cte:+.2f} m" if cte is not None else ""))
            if action is not None:
                lines.append("action " + np.array2string(np.atleast_1d(np.asarray(action, np.float64)), precision=2))
            frame = overlay(frame, lines)
        frame = frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]  # even sizes for H.264
        self._writer.append_data(frame)
        if self.frames % 10 == 0 and len(self.thumbnails) < self._keep:
            self.thumbnails.append(frame[::2, ::2])
        self.frames += 1

    def strip(self) -> np.ndarray | None:
        """The thumbnails side by side, (H, W * k, 3) uint8, or None."""
        return np.concatenate(self.thumbnails, axis=1) if self.thumbnails else None

    def _open(self, path: Path, fps: float) -> None:
        self._close_writer()
        if path.suffix.lower() == ".gif":
            self._writer = imageio.get_writer(path, mode="I", duration=1000 / fps, loop=0)
        else:
            self._writer = imageio.get_writer(path, fps=fps, codec="libx264", macro_block_size=2,
                                              quality=7, ffmpeg_log_level="error")
        self.paths.append(path)

    def _close_writer(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def close(self) -> list[Path]:
        self._close_writer()
        return self.paths
