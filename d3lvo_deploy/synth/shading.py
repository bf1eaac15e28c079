"""Procedural materials: albedo as a function of world-anchored metric texture coordinates.

Noise octaves fade out once a pixel's footprint exceeds their wavelength (a poor man's mip-map),
so distant asphalt does not sparkle differently from frame to frame and confuse optical flow.
"""

from __future__ import annotations

import numpy as np

from .world import (ASPHALT, CAR, FACADE, FOLIAGE, GLASS, KERB, POLE, ROOF, SIDEWALK, TRUNK, VERGE,
                    StreetStyle)

TEX = 256


def noise_texture(seed: int) -> np.ndarray:
    """Tileable band-limited noise, zero mean, unit std, features ~4 texels wide."""
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((TEX, TEX))
    f = np.fft.fftfreq(TEX)
    gauss = np.exp(-2 * (np.pi * 1.5) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))  # sigma 1.5 texels, periodic
    t = np.real(np.fft.ifft2(np.fft.fft2(white) * gauss))
    return ((t - t.mean()) / t.std()).astype(np.float32)


def sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear, wrapped lookup at texel coordinates of any magnitude."""
    x = np.mod(np.asarray(x, dtype=np.float64), TEX)
    y = np.mod(np.asarray(y, dtype=np.float64), TEX)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    x0 %= TEX
    y0 %= TEX
    x1, y1 = (x0 + 1) % TEX, (y0 + 1) % TEX
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def octaves(tex: np.ndarray, uv: np.ndarray, footprint: np.ndarray, waves: tuple[float, ...],
            amps: tuple[float, ...], offset: float = 0.0) -> np.ndarray:
    out = np.zeros(len(uv), dtype=np.float32)
    for i, (lam, amp) in enumerate(zip(waves, amps)):
        w = np.clip(2.0 - 4.0 * footprint / lam, 0.0, 1.0)
        if not np.any(w > 0):
            continue
        shift = 37.0 * i + offset
        out += amp * w * sample(tex, uv[:, 0] * 4.0 / lam + shift, uv[:, 1] * 4.0 / lam + 1.7 * shift)
    return out


def _frac(x: np.ndarray) -> np.ndarray:
    return x - np.floor(x)


def lane_marks(s: np.ndarray, lat: np.ndarray, st: StreetStyle) -> np.ndarray:
    """True where a painted line is: dashed between lanes, solid at the carriageway edges."""
    half = 0.06
    right_edge = st.lane / 2
    left_edge = -(st.lane / 2 + st.lane * st.left_lanes)
    mark = (np.abs(lat - right_edge) < half) | (np.abs(lat - left_edge) < half)
    dash = _frac(s / 9.0) < 0.35
    for k in range(st.left_lanes):
        mark |= (np.abs(lat - (-st.lane / 2 - k * st.lane)) < half) & dash
    return mark


def albedo(material: np.ndarray, colour: np.ndarray, variant: np.ndarray, uv: np.ndarray,
           footprint: np.ndarray, tex: np.ndarray, st: StreetStyle) -> np.ndarray:
    """(N,3) albedo in [0,1] for surface hits."""
    out = colour.astype(np.float32).copy()
    mod = np.ones(len(material), dtype=np.float32)

    def apply(mask: np.ndarray, waves, amps, off=0.0) -> None:
        if np.any(mask):
            mod[mask] += octaves(tex, uv[mask], footprint[mask], waves, amps, off)

    m = material == ASPHALT
    apply(m, (0.04, 0.25, 1.5), (0.22, 0.12, 0.10))
    if np.any(m):
        paint = np.zeros(len(material), dtype=bool)
        paint[m] = lane_marks(uv[m, 0], uv[m, 1], st)
        out[paint] = (0.82, 0.82, 0.8)
    m = material == SIDEWALK
    apply(m, (0.03, 0.2), (0.12, 0.08), 11.0)
    if np.any(m):
        g = (_frac(uv[m, 0] / 0.4) < 0.06) | (_frac(uv[m, 1] / 0.4) < 0.06)
        mod[np.nonzero(m)[0][g]] *= 0.7
    apply(material == KERB, (0.03, 0.3), (0.15, 0.08), 23.0)
    apply(material == VERGE, (0.05, 0.3, 2.0), (0.35, 0.2, 0.15), 31.0)
    m = material == FACADE
    apply(m, (0.03, 0.15, 1.0), (0.15, 0.1, 0.08), 41.0)
    if np.any(m):
        idx = np.nonzero(m)[0]
        fx = _frac(uv[idx, 0] / variant[idx])
        fy = _frac(uv[idx, 1] / 3.0)
        win = (fx > 0.25) & (fx < 0.75) & (fy > 0.3) & (fy < 0.8) & (uv[idx, 1] > 1.0)
        out[idx[win]] = (0.12, 0.14, 0.18)
        frame = (~win) & (fx > 0.2) & (fx < 0.8) & (fy > 0.25) & (fy < 0.85) & (uv[idx, 1] > 1.0)
        mod[idx[frame]] *= 0.6
    apply(material == ROOF, (0.05, 0.5), (0.2, 0.1), 53.0)
    apply(material == CAR, (0.1, 0.6), (0.05, 0.04), 59.0)
    apply(material == GLASS, (0.2,), (0.15,), 61.0)
    apply(material == POLE, (0.05, 0.5), (0.1, 0.05), 67.0)
    apply(material == FOLIAGE, (0.05, 0.2, 0.8), (0.4, 0.3, 0.2), 71.0)
    apply(material == TRUNK, (0.02, 0.1), (0.2, 0.1), 73.0)
    return np.clip(out * np.clip(mod, 0.2, 2.0)[:, None], 0.0, 1.0)


def sky(directions: np.ndarray, tex: np.ndarray) -> np.ndarray:
    """Sky colour by elevation, with clouds anchored to direction (they do not move with the car)."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    elev = np.clip(-d[:, 1], 0.0, 1.0)
    az = np.arctan2(d[:, 0], d[:, 2])
    horizon = np.array([0.86, 0.88, 0.92], dtype=np.float32)
    zenith = np.array([0.42, 0.58, 0.85], dtype=np.float32)
    a = np.clip(elev * 3.0, 0.0, 1.0)[:, None]
    col = horizon * (1 - a) + zenith * a
    cloud = sample(tex, az * 40.0, elev * 120.0) * 0.5 + sample(tex, az * 120.0 + 9, elev * 360.0) * 0.25
    c = np.clip(cloud, 0, 1)[:, None]
    return col * (1 - 0.6 * c) + 0.95 * 0.6 * c
