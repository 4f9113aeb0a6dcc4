"""Analytic shapes with exact signed distances: test truth and sample data.

Every shape offers ``sample(n, noise=0, seed=0) -> (points, normals)`` with
points spread uniformly by area and outward unit normals,
``signed_distance(x)`` (negative inside, positive outside) and, where it has
one, a closed-form ``genus``.  Noise is Gaussian, along the normal, with the
given standard deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from o3drbf.validation import check_number

__all__ = ["Sphere", "Torus", "TorusStack", "Cube", "cube_corner"]


def _noisy(points, normals, noise, rng):
    noise = check_number("noise", noise, low=0.0)
    if noise > 0:
        points = points + normals * rng.normal(0.0, noise, size=(len(points), 1))
    return points, normals


def _count(n):
    return check_number("n", n, low=1, integer=True)


@dataclass(frozen=True)
class Sphere:
    radius: float = 1.0
    center: tuple = (0.0, 0.0, 0.0)
    genus = 0

    def sample(self, n: int, noise: float = 0.0, seed: int = 0):
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(_count(n), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return _noisy(np.asarray(self.center) + self.radius * d, d, noise, rng)

    def signed_distance(self, x):
        return np.linalg.norm(np.asarray(x, float) - self.center, axis=-1) - self.radius


@dataclass(frozen=True)
class Torus:
    """A torus around the z axis: major radius ``R``, tube radius ``r``.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Torus
    >>> points, normals = Torus(0.6, 0.25).sample(500, seed=1)
    >>> ring = np.hypot(points[:, 0], points[:, 1]) - 0.6  # distance from the tube's centre circle, in its plane
    >>> bool(np.allclose(np.hypot(ring, points[:, 2]), 0.25)), normals.shape
    (True, (500, 3))
    """

    R: float = 0.7
    r: float = 0.25
    center: tuple = (0.0, 0.0, 0.0)
    genus = 1

    def sample(self, n: int, noise: float = 0.0, seed: int = 0):
        rng = np.random.default_rng(seed)
        n = _count(n)
        u = np.empty(0)
        v = np.empty(0)
        # Area element (R + r cos v): rejection sampling keeps it uniform.
        while u.size < n:
            m = 2 * (n - u.size) + 16
            uu = rng.uniform(0, 2 * np.pi, m)
            vv = rng.uniform(0, 2 * np.pi, m)
            keep = rng.uniform(0, self.R + self.r, m) < self.R + self.r * np.cos(vv)
            u = np.concatenate([u, uu[keep]])
            v = np.concatenate([v, vv[keep]])
        u, v = u[:n], v[:n]
        normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
        ring = np.stack([self.R * np.cos(u), self.R * np.sin(u), np.zeros(n)], axis=1)
        points = np.asarray(self.center) + ring + self.r * normals
        return _noisy(points, normals, noise, rng)

    def signed_distance(self, x):
        p = np.asarray(x, float) - self.center
        q = np.hypot(p[..., 0], p[..., 1]) - self.R
        return np.hypot(q, p[..., 2]) - self.r

    @property
    def area(self) -> float:
        return 4 * np.pi**2 * self.R * self.r


@dataclass(frozen=True)
class TorusStack:
    """``count`` tori stacked along z (the paper's 'towers' data set, idealized)."""

    count: int = 3
    R: float = 0.6
    r: float = 0.2
    gap: float = 0.1

    @property
    def tori(self):
        pitch = 2 * self.r + self.gap
        z0 = -(self.count - 1) * pitch / 2
        return [Torus(self.R, self.r, (0.0, 0.0, z0 + i * pitch)) for i in range(self.count)]

    @property
    def genus(self):
        return self.count

    def sample(self, n: int, noise: float = 0.0, seed: int = 0):
        n = _count(n)
        parts = [t.sample(n // self.count + (i < n % self.count), 0.0, seed + i) for i, t in enumerate(self.tori)]
        pts = np.concatenate([p for p, _ in parts])
        nrm = np.concatenate([q for _, q in parts])
        return _noisy(pts, nrm, noise, np.random.default_rng(seed + 1000))

    def signed_distance(self, x):
        return np.min([t.signed_distance(x) for t in self.tori], axis=0)


@dataclass(frozen=True)
class Cube:
    """An axis-aligned cube of half side ``half``: sharp edges and corners."""

    half: float = 0.5
    genus = 0

    def sample(self, n: int, noise: float = 0.0, seed: int = 0, faces=(0, 1, 2, 3, 4, 5)):
        """Uniform on the listed faces: face k is axis k % 3, sign + for k < 3."""
        rng = np.random.default_rng(seed)
        n = _count(n)
        f = rng.choice(np.asarray(faces), size=n)
        pts = rng.uniform(-self.half, self.half, size=(n, 3))
        axis = f % 3
        sign = np.where(f < 3, 1.0, -1.0)
        pts[np.arange(n), axis] = sign * self.half
        normals = np.zeros((n, 3))
        normals[np.arange(n), axis] = sign
        return _noisy(pts, normals, noise, rng)

    def signed_distance(self, x):
        q = np.abs(np.asarray(x, float)) - self.half
        outside = np.linalg.norm(np.maximum(q, 0), axis=-1)
        inside = np.minimum(q.max(axis=-1), 0)
        return outside + inside


def cube_corner(n: int = 2000, noise: float = 0.0, seed: int = 0, half: float = 0.5):
    """The paper's Fig. 2 input: a range image of a cube's corner.

    Points on the three faces x = +half, y = +half, z = +half (what a range
    camera looking from (1, 1, 1) sees), with outward normals.
    """
    return Cube(half).sample(n, noise, seed, faces=(0, 1, 2))
