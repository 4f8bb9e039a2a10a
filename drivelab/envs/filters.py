"""Observation filters for image observations, as Gymnasium wrappers applied in config order.

    obs_filters: [grayscale, {crop: {top: 20}}, {resize: {shape: [64, 64]}}, sobel, {binarize: {threshold: 0.2}}, {frame_stack: {n: 4}}]

Gymnasium's own wrappers do grayscale (``GrayscaleObservation``), resize (``ResizeObservation``),
frame stacking (``FrameStackObservation``) and arbitrary transforms (``TransformObservation``);
this module adds what is missing as small pure functions on (H, W, C) arrays: to_float, crop,
Sobel edges, binarise, normalise, and resize for images with more than 4 channels (MetaDrive's
top-down view has 5). Images keep a trailing channel axis throughout, so the CNN encoder sees
(H, W, C).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import FrameStackObservation, GrayscaleObservation, ResizeObservation, TransformObservation

from drivelab.errors import DrivelabError

# SciPy and OpenCV are imported by the filters that use them, not here: every `import drivelab`
# imports this module (a fifth of a second saved on `drivelab --help`).


def to_float(image: np.ndarray) -> np.ndarray:
    """uint8 [0, 255] -> float32 [0, 1]."""
    return image.astype(np.float32) / 255.0


def crop(image: np.ndarray, top: int = 0, bottom: int = 0, left: int = 0, right: int = 0) -> np.ndarray:
    """Remove `top`/`bottom` rows and `left`/`right` columns (e.g. the sky above a road camera's horizon)."""
    h, w = image.shape[:2]
    return image[top:h - bottom, left:w - right]


def sobel(image: np.ndarray) -> np.ndarray:
    """Gradient magnitude sqrt(Gx^2 + Gy^2) of each channel with 3x3 Sobel kernels, float32,
    scaled to [0, 1] by its maximum possible value (4 * sqrt(2) * the input range)."""
    from scipy import ndimage

    peak = 255.0 if image.dtype == np.uint8 else 1.0
    out = np.empty(image.shape, np.float32)
    for c in range(image.shape[-1]):  # per channel: a 3-D sobel would also smooth across channels
        x = image[..., c].astype(np.float32)
        gx = ndimage.sobel(x, axis=1, mode="nearest")
        gy = ndimage.sobel(x, axis=0, mode="nearest")
        out[..., c] = np.hypot(gx, gy) / np.float32(4 * np.sqrt(2) * peak)
    return out


def resize(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area-resample an (H, W, C) image to `shape` = (height, width) for any number of channels.

    OpenCV resizes at most 4 channels at once; MetaDrive's top-down image has 5 (and a frame
    stack more), so the channels go through in groups of up to 4.
    """
    import cv2

    height, width = shape
    groups = [cv2.resize(image[..., c:c + 4], (width, height), interpolation=cv2.INTER_AREA)
              for c in range(0, image.shape[-1], 4)]
    return np.concatenate([g.reshape(height, width, -1) for g in groups], axis=-1)


def binarize(image: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """1.0 where the pixel exceeds `threshold` (in the image's own units), else 0.0."""
    return (image > threshold).astype(np.float32)


def normalize(image: np.ndarray, mean: float = 0.5, std: float = 0.5) -> np.ndarray:
    """(x - mean) / std with fixed constants (no running statistics to lose between runs)."""
    return ((image - mean) / std).astype(np.float32)


def _box(space: gym.spaces.Box, sample: np.ndarray, low: float, high: float) -> gym.spaces.Box:
    return gym.spaces.Box(low, high, sample.shape, sample.dtype)


def _transform(env: gym.Env, fn, low: float, high: float) -> gym.Env:
    sample = fn(env.observation_space.sample())
    return TransformObservation(env, fn, _box(env.observation_space, sample, low, high))


def _stack_to_channels(env: gym.Env) -> gym.Env:
    """(n, H, W, C) from FrameStackObservation -> (H, W, n * C), the layout the CNN expects."""
    space = env.observation_space
    n, h, w, c = space.shape

    def merge(stacked: np.ndarray) -> np.ndarray:
        return np.moveaxis(stacked, 0, 2).reshape(h, w, n * c)

    low = float(np.min(space.low)) if np.isfinite(np.min(space.low)) else -np.inf
    high = float(np.max(space.high)) if np.isfinite(np.max(space.high)) else np.inf
    return TransformObservation(env, merge, gym.spaces.Box(low, high, (h, w, n * c), space.dtype))


def apply_filters(env: gym.Env, specs: list[Any]) -> gym.Env:
    """Wrap ``env`` with each filter of ``specs`` in order; a spec is a name or {name: params}."""
    for spec in specs:
        if isinstance(spec, str):
            name, params = spec, {}
        elif isinstance(spec, dict) and len(spec) == 1:
            (name, params), = spec.items()
            if not isinstance(params, (dict, type(None))):
                raise DrivelabError(f"env.obs_filters.{name}: parameters are a mapping such as "
                                    f"{{frame_stack: {{n: 4}}}}, got {params!r}")
            params = dict(params or {})
        else:
            raise DrivelabError(f"env.obs_filters: each filter is a name or {{name: params}}, got {spec!r}")
        space = env.observation_space
        if not (isinstance(space, gym.spaces.Box) and len(space.shape) == 3):
            raise DrivelabError(f"env.obs_filters.{name}: needs (H, W, C) image observations, got {space}")
        try:
            if name == "grayscale":
                env = GrayscaleObservation(env, keep_dim=True)
            elif name == "resize" and space.shape[-1] <= 4:
                env = ResizeObservation(env, tuple(params.pop("shape")))
            elif name == "resize":  # more channels than OpenCV takes at once
                shape = tuple(int(n) for n in params.pop("shape"))
                env = _transform(env, lambda x, shape=shape: resize(x, shape),
                                 float(np.min(space.low)), float(np.max(space.high)))
            elif name == "frame_stack":
                env = _stack_to_channels(FrameStackObservation(env, int(params.pop("n", 4))))
            elif name == "to_float":
                env = _transform(env, to_float, 0.0, 1.0)
            elif name == "crop":
                env = _transform(env, lambda x, p=dict(params): crop(x, **p), float(np.min(space.low)), float(np.max(space.high)))
                params = {}
            elif name == "sobel":
                env = _transform(env, sobel, 0.0, 1.0)
            elif name == "binarize":
                env = _transform(env, lambda x, p=dict(params): binarize(x, **p), 0.0, 1.0)
                params = {}
            elif name == "normalize":
                p = dict(params)
                env = _transform(env, lambda x: normalize(x, **p), -np.inf, np.inf)
                params = {}
            else:
                raise DrivelabError(f"env.obs_filters: unknown filter '{name}' (grayscale, crop, resize, sobel, "
                                    "binarize, frame_stack, normalize, to_float)")
        except (TypeError, KeyError, ValueError) as exc:
            raise DrivelabError(f"env.obs_filters.{name}: bad parameters {spec!r} ({exc})") from None
        if params:
            raise DrivelabError(f"env.obs_filters.{name}: unknown parameter(s) {', '.join(params)}")
    return env
