#!/usr/bin/env python3
"""Reference outputs of the natural HHD for the Rust tests (fixtures/hhd/).

pynhhd 1.1 (the authors' package) could not be installed from the package
index here, so this script is our own numpy/scipy transcription of the exact
definition of the natural HHD (Bhatia et al. 2014), built from the same library calls the
reference makes: numpy.gradient for every derivative, the Green's function
ln(r)/(2 pi) on a (2ny-1) x (2nx-1) offset grid with r(0) = (dx+dy)/4, and
scipy.signal.fftconvolve(..., mode='same') times dx*dy for the potentials.
On the smaller cases it also checks the convolution against a direct sum.

Inputs are rounded to float32 first (the Rust API takes f32 flows), then
everything is float64. Usage: python3 tools/nhhd_reference.py [OUTDIR]
(needs numpy and scipy; default OUTDIR fixtures/hhd).
"""
import os
import sys

import numpy as np
from scipy import signal


def divcurl(u, v, dx, dy):
    dudy, dudx = np.gradient(u, dy, dx)
    dvdy, dvdx = np.gradient(v, dy, dx)
    return dudx + dvdy, dvdx - dudy


def green(ny, nx, dx, dy):
    ky, kx = np.indices((2 * ny - 1, 2 * nx - 1), dtype=np.float64)
    r = np.hypot((ky - (ny - 1)) * dy, (kx - (nx - 1)) * dx)
    r[ny - 1, nx - 1] = 0.5 * (dx + dy) / 2.0
    return np.log(r) * (0.5 / np.pi)


def nhhd(u, v, dx, dy):
    ny, nx = u.shape
    div, curl = divcurl(u, v, dx, dy)
    g = green(ny, nx, dx, dy)
    D = signal.fftconvolve(div, g, mode="same") * (dx * dy)
    R = signal.fftconvolve(curl, g, mode="same") * (dx * dy)
    Dy, Dx = np.gradient(D, dy, dx)
    Ry, Rx = np.gradient(R, dy, dx)
    d = (Dx, Dy)
    r = (-Ry, Rx)
    h = (u - (d[0] + r[0]), v - (d[1] + r[1]))
    return dict(div=div, curl=curl, D=D, R=R, d_u=d[0], d_v=d[1],
                r_u=r[0], r_v=r[1], h_u=h[0], h_v=h[1])


def direct(f, dx, dy):
    ny, nx = f.shape
    g = green(ny, nx, dx, dy)
    out = np.zeros_like(f)
    for my in range(ny):
        for mx in range(nx):
            win = g[my:my + ny, mx:mx + nx][::-1, ::-1]
            out[my, mx] = np.sum(f * win)
    return out * (dx * dy)


def analytic(ny, nx, dx, dy, seed):
    """Gaussian potential gradient + rotated stream-function gradient + linear
    harmonic part + a little noise, on the grid (x = j dx, y = i dy)."""
    rng = np.random.default_rng(seed)
    y, x = np.indices((ny, nx), dtype=np.float64)
    x *= dx
    y *= dy
    W, H = (nx - 1) * dx, (ny - 1) * dy
    cx, cy, s = 0.45 * W, 0.55 * H, 0.2 * max(W, H) + 1e-9
    phi = -np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    ex, ey = 0.6 * W, 0.4 * H
    psi = 0.7 * np.exp(-((x - ex) ** 2 + (y - ey) ** 2) / (2 * (0.8 * s) ** 2))
    # grad phi + (-dpsi/dy, dpsi/dx)
    u = -(x - cx) / (s * s) * phi + (y - ey) / (0.8 * s) ** 2 * psi
    v = -(y - cy) / (s * s) * phi - (x - ex) / (0.8 * s) ** 2 * psi
    u = u + 0.3 + 0.01 * x - 0.02 * y
    v = v - 0.2 - 0.02 * x - 0.01 * y
    u = u + 0.01 * rng.standard_normal(u.shape)
    v = v + 0.01 * rng.standard_normal(v.shape)
    return u, v


def press(ny, nx, dx, dy):
    """Radial outward flow around the centre, like a press on the skin."""
    y, x = np.indices((ny, nx), dtype=np.float64)
    x = (x - (nx - 1) / 2) * dx
    y = (y - (ny - 1) / 2) * dy
    s = 0.25 * min(nx * dx, ny * dy)
    a = np.exp(-(x * x + y * y) / (2 * s * s))
    return 0.8 * x / s * a, 0.8 * y / s * a


CASES = [
    # name, ny, nx, dx, dy, field
    ("analytic_17x23", 17, 23, 0.7, 1.3, lambda: analytic(17, 23, 0.7, 1.3, 1)),
    ("press_32x32", 32, 32, 1.0, 1.0, lambda: press(32, 32, 1.0, 1.0)),
    ("random_12x40", 12, 40, 2.0, 0.5,
     lambda: tuple(np.random.default_rng(7).standard_normal((2, 12, 40)))),
]


def main():
    outdir = sys.argv[1] if len(sys.argv) > 1 else "fixtures/hhd"
    for name, ny, nx, dx, dy, field in CASES:
        u, v = field()
        u = u.astype(np.float32).astype(np.float64)
        v = v.astype(np.float32).astype(np.float64)
        res = nhhd(u, v, dx, dy)
        for key, pot in (("D", "div"), ("R", "curl")):
            ref = direct(res[pot], dx, dy)
            err = np.max(np.abs(ref - res[key])) / np.max(np.abs(ref))
            assert err < 1e-12, (name, key, err)
        d = os.path.join(outdir, name)
        os.makedirs(d, exist_ok=True)
        np.save(os.path.join(d, "u.npy"), u)
        np.save(os.path.join(d, "v.npy"), v)
        for k, a in res.items():
            np.save(os.path.join(d, k + ".npy"), np.ascontiguousarray(a, dtype="<f8"))
        with open(os.path.join(d, "spacing.txt"), "w") as f:
            f.write(f"{dx!r} {dy!r}\n")
        print(name, u.shape, dx, dy, "ok")


if __name__ == "__main__":
    main()
