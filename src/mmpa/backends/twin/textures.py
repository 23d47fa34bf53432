"""Procedural, seeded textures for the twin's scenes (logos, letter tapes, wood, floor).

Each function returns an RGB ``uint8`` image ``(H, W, 3)``; :func:`png_bytes` encodes it for
MuJoCo's asset dictionary. Same seed, same pixels: every twin world draws the same textures
from the same generator states, so each function remembers its images by the generator's state
and arguments (:func:`_memo`) and a later world takes them from there, the generator advanced
as a drawing would have left it.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import string
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import imsave
from matplotlib.patches import Circle, Polygon, Rectangle

__all__ = ["backboard", "floor", "letters", "logo", "png_bytes", "wall", "wood"]

_PALETTE = np.array(
    [
        [0.85, 0.15, 0.15],
        [0.10, 0.35, 0.80],
        [0.05, 0.60, 0.30],
        [0.95, 0.70, 0.05],
        [0.50, 0.15, 0.60],
        [0.10, 0.10, 0.10],
        [0.95, 0.45, 0.10],
        [0.00, 0.55, 0.65],
    ]
)


_MEMO_SIZE = 64  # images kept per function (a scene draws at most a dozen of each)
_PNG: OrderedDict[bytes, bytes] = OrderedDict()


def _remember(cache: OrderedDict, key: Any, value: Any) -> None:
    cache[key] = value
    if len(cache) > _MEMO_SIZE:
        cache.popitem(last=False)


def _memo(fn: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """``fn(..., rng, ...)`` remembered by its other arguments and ``rng``'s state: a hit
    returns a copy of the image and sets ``rng`` to the state the drawing left it in."""
    cache: OrderedDict[str, tuple[np.ndarray, dict]] = OrderedDict()

    @functools.wraps(fn)
    def drawn(*args: Any, **kwargs: Any) -> np.ndarray:
        rng = next(a for a in (*args, *kwargs.values()) if isinstance(a, np.random.Generator))
        rest = [a for a in args if a is not rng], {k: v for k, v in kwargs.items() if v is not rng}
        key = json.dumps([repr(rest), rng.bit_generator.state], sort_keys=True, default=str)
        if key in cache:
            img, after = cache[key]
            rng.bit_generator.state = after
            return img.copy()
        img = fn(*args, **kwargs)
        _remember(cache, key, (img.copy(), rng.bit_generator.state))
        return img

    return drawn


def png_bytes(img: np.ndarray) -> bytes:
    """Encode an RGB uint8 image as PNG (remembered by the pixels' digest)."""
    img = np.ascontiguousarray(img)
    key = hashlib.blake2b(img.tobytes(), digest_size=16).digest() + repr(img.shape).encode()
    if key not in _PNG:
        buf = io.BytesIO()
        imsave(buf, img, format="png")
        _remember(_PNG, key, buf.getvalue())
    return _PNG[key]


def _canvas(w: int, h: int, bg: np.ndarray) -> tuple[Figure, object]:
    fig = Figure(figsize=(w / 100.0, h / 100.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, w)
    ax.set_ylim(0, h)
    ax.axis("off")
    fig.patch.set_facecolor(tuple(bg))
    return fig, ax


def _to_rgb(fig: Figure) -> np.ndarray:
    canvas = fig.canvas
    canvas.draw()  # type: ignore[attr-defined]
    rgba = np.asarray(canvas.buffer_rgba())  # type: ignore[attr-defined]
    return np.ascontiguousarray(rgba[..., :3])


def _random_word(rng: np.random.Generator, n: int) -> str:
    return "".join(rng.choice(list(string.ascii_uppercase + string.digits), n))


@_memo
def logo(rng: np.random.Generator, w: int = 256, h: int = 128) -> np.ndarray:
    """A company-logo-like patch: colored shapes and a short word on a plain background."""
    bg = np.array([1.0, 1.0, 1.0]) * rng.uniform(0.85, 1.0)
    fig, ax = _canvas(w, h, bg)

    for _ in range(int(rng.integers(2, 5))):
        c = _PALETTE[rng.integers(len(_PALETTE))]
        kind = rng.integers(3)
        x, y = rng.uniform(0.05 * w, 0.45 * w), rng.uniform(0.2 * h, 0.8 * h)
        s = rng.uniform(0.12, 0.3) * h
        if kind == 0:
            ax.add_patch(Circle((x, y), s, color=c))
        elif kind == 1:
            ax.add_patch(
                Rectangle((x - s, y - s / 2), 2 * s, s, angle=rng.uniform(-40, 40), color=c)
            )
        else:
            pts = np.array([x, y]) + rng.uniform(-s, s, size=(3, 2))
            ax.add_patch(Polygon(pts, color=c))
    ax.text(
        0.52 * w,
        0.5 * h,
        _random_word(rng, int(rng.integers(3, 5))),
        fontsize=h * 0.28,
        fontweight="bold",
        color=_PALETTE[rng.integers(len(_PALETTE))],
        va="center",
    )
    return _to_rgb(fig)


@_memo
def letters(text: str, rng: np.random.Generator, w: int = 384, h: int = 64) -> np.ndarray:
    """A strip of tape with printed letters (paper 000: 'letters printed on the tape')."""
    bg = np.array([0.98, 0.92, 0.35]) if rng.uniform() < 0.5 else np.array([0.97, 0.97, 0.97])
    fig, ax = _canvas(w, h, bg)
    ax.text(
        w / 2,
        h / 2,
        text,
        fontsize=h * 0.55,
        fontweight="bold",
        family="monospace",
        color=(0.05, 0.05, 0.05),
        ha="center",
        va="center",
    )
    return _to_rgb(fig)


@_memo
def backboard(rng: np.random.Generator, w: int = 512, h: int = 256) -> np.ndarray:
    """A poster board: several logos and words tiled over a light background."""
    img = np.full((h, w, 3), 235, np.uint8)
    for i in range(2):
        for j in range(2):
            patch = logo(rng, w // 2 - 16, h // 2 - 16)
            y0, x0 = i * (h // 2) + 8, j * (w // 2) + 8
            img[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]] = patch
    return img


@_memo
def wood(rng: np.random.Generator, w: int = 256, h: int = 256) -> np.ndarray:
    """Desk-top wood grain: sinusoidal rings with noise."""
    y, x = np.mgrid[0:h, 0:w] / float(w)
    phase = rng.uniform(0, 2 * np.pi)
    grain = np.sin(40 * x + 6 * np.sin(3 * y + phase) + rng.normal(0, 0.3, (h, w)))
    base = np.array([0.62, 0.45, 0.28])
    img = base[None, None, :] * (0.85 + 0.12 * grain[..., None])
    img += rng.normal(0, 0.02, img.shape)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


@_memo
def floor(rng: np.random.Generator, w: int = 256, h: int = 256) -> np.ndarray:
    """Speckled floor tiles."""
    img = np.full((h, w, 3), 0.55) + rng.normal(0, 0.05, (h, w, 1))
    img[:: w // 4, :, :] = 0.4
    img[:, :: w // 4, :] = 0.4
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


@_memo
def wall(rng: np.random.Generator, w: int = 128, h: int = 128) -> np.ndarray:
    """Painted wall with faint noise."""
    img = np.array([0.88, 0.87, 0.82])[None, None, :] + rng.normal(0, 0.015, (h, w, 1))
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)
