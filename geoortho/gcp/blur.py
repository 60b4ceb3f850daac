"""A photo's motion blur: estimated from its own gradients, as a kernel, as a path a point spreads along,
and undone (Wiener) before a detector looks.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def estimate_motion_blur(gray: np.ndarray, tile_px: int = 128, max_tiles: int = 24) -> tuple[float, float]:
    """A photo's motion blur (length px, direction deg from the x axis, anticlockwise in the image)
    from the cepstrum of its texture: a straight blur of length L puts a negative peak at L along
    its direction (the zeros of its sinc spectrum repeat every 1/L). (0, 0) when none stands out."""
    h, w = gray.shape[:2]
    if h < tile_px or w < tile_px:
        return 0.0, 0.0
    ny, nx = h // tile_px, w // tile_px
    # the most textured tiles, ranked on every 4th pixel (16x cheaper; a ranking needs no more)
    sub = gray[: ny * tile_px : 4, : nx * tile_px : 4].astype(np.float32)
    var = sub.reshape(ny, tile_px // 4, nx, tile_px // 4).var(axis=(1, 3)).ravel()
    keep = [divmod(int(i), nx) for i in np.argsort(-var)[:max_tiles] if var[i] > 4.0]
    if not keep:
        return 0.0, 0.0
    win = np.outer(np.hanning(tile_px), np.hanning(tile_px)).astype(np.float32)
    power = np.zeros((tile_px, tile_px), np.float64)
    for ty, tx in keep:
        t = gray[ty * tile_px : (ty + 1) * tile_px, tx * tile_px : (tx + 1) * tile_px].astype(np.float32)
        spec = cv2.dft((t - t.mean()) * win, flags=cv2.DFT_COMPLEX_OUTPUT)
        power += cv2.magnitude(spec[..., 0], spec[..., 1]) ** 2
    cep = np.fft.fftshift(np.real(np.fft.ifft2(np.log(power / len(keep) + 1e-3))))
    c = tile_px // 2
    yy, xx = np.mgrid[-c : tile_px - c, -c : tile_px - c]
    r = np.hypot(xx, yy)
    # a real image's cepstrum is symmetric: its peak at (dx, dy) is also at (-dx, -dy), equal to the
    # last bit, and which one argmin took changed from run to run (seen after other work in the same
    # process: the angle then differed by 1e-14 degrees, and marker fits that start from it by up to
    # 0.3 px): one half-plane only
    ring = (r >= 2.5) & (r <= tile_px / 3) & ((yy < 0) | ((yy == 0) & (xx > 0)))
    vals = np.where(ring, cep, np.inf)
    k = int(np.argmin(vals))
    ky, kx = divmod(k, tile_px)
    spread = float(np.std(cep[ring]))
    if -cep[ky, kx] < 4.0 * spread:
        return 0.0, 0.0
    dx, dy = xx[ky, kx], yy[ky, kx]
    return float(math.hypot(dx, dy)), float(math.degrees(math.atan2(-dy, dx)) % 180.0)


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """A straight motion-blur kernel: the path of a point moving ``length_px`` at ``angle_deg``
    (anticlockwise from the x axis as seen), its exact length: a camera's blur is not a whole
    number of pixels (an odd-sized line kernel made 7.6 px a 9 px blur while the truth said 7.6).
    The path is sampled finely and spread over the pixels it crosses (bilinear)."""
    n = max(2, int(math.ceil(16 * length_px)))
    t = ((np.arange(n) + 0.5) / n - 0.5) * length_px
    a = math.radians(angle_deg)
    r = int(math.ceil(length_px / 2)) + 1
    x, y = r + t * math.cos(a), r - t * math.sin(a)
    return spread_path(x, y, np.ones_like(t), 2 * r + 1)


def spread_path(x: np.ndarray, y: np.ndarray, weight: np.ndarray, size: int) -> np.ndarray:
    """A kernel ``size`` square from the samples of a path (pixel x, y, and each sample's weight),
    each spread over the four pixels around it (bilinear); normalised to sum 1."""
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((size, size), np.float64)
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), wgt * weight)
    result: np.ndarray = (kernel / kernel.sum()).astype(np.float32)
    return result


#: The Wiener filter's noise-to-signal power (of a spectrum normalised to the kernel's): of 0.003,
#: 0.01 and 0.03, the first decoded the most blurred markers (a degraded flight and three small
#: surveys, 4-10 px of blur on 14-16 px markers: 84, 29, 22 and 30 of 106, 47, 47 and 47).
DEBLUR_NOISE = 0.003


def deblurred(gray: np.ndarray, blur: tuple[float, float]) -> np.ndarray:
    """A grey crop with a straight motion ``blur`` (length px, direction deg) undone by a Wiener
    filter, as uint8. The blur's sinc spectrum has zeros that no inverse crosses: the filter leaves
    those frequencies out, and a marker's cells come back sharp enough for the detector to read,
    its centre as well as a model fit places it (:func:`.detect._search`)."""
    img = gray.astype(np.float64)
    kernel = motion_kernel(*blur).astype(np.float64)
    pad = np.zeros(img.shape)
    kh, kw = kernel.shape
    pad[:kh, :kw] = kernel
    pad = np.roll(pad, (-(kh // 2), -(kw // 2)), axis=(0, 1))  # centred on the origin: no shift
    H = np.fft.rfft2(pad)
    out = np.fft.irfft2(np.fft.rfft2(img) * np.conj(H) / (np.abs(H) ** 2 + DEBLUR_NOISE), s=img.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
