"""Radial basis functions: the multi-order basis, thin-plate r^3 and the Gaussian.

Every kernel is a small immutable object with

- ``kernel(r)``: the value phi(r) for distances ``r >= 0`` (any shape);
- ``kernel.derivative(r)``: d phi / d r;
- ``kernel.derivative_over_r(r)``: phi'(r) / r, finite at r = 0, which is
  what gradients need (grad phi(|x - c|) = phi'(r)/r * (x - c));
- ``kernel.polynomial_degree``: the degree of the polynomial P(x) that spans
  the null space of the kernel's energy (0: a constant, 1: linear);
- ``kernel.positive_definite``: whether Phi + diag(lambda) is symmetric
  positive definite (so Cholesky applies) or only conditionally so.

The table :data:`KERNELS` maps a name to its class and is the single source
of truth for which kernels exist (``make_kernel("multiorder", delta=10)``).

Notes
-----
The multi-order basis is the Green's function of the energy

    delta^2 |grad f|^2 + |Hess f|^2 + tau^2 |third derivatives|^2,

whose 3-D Fourier symbol is ``1 / (delta^2 k^2 + k^4 + tau^2 k^6)``.  With
``a = sqrt(v)``, ``b = sqrt(w)`` the roots of ``tau^2 s^2 - s + delta^2`` (in
``s = a^2``), partial fractions give

    phi(r) = 1/(4 pi delta^2 r) * (1 + A e^{-a r} + B e^{-b r}),
    A = b^2 / (a^2 - b^2),  B = -a^2 / (a^2 - b^2).

Here it is evaluated as a divided difference in (a, b),

    phi(r) = -(a b)^2 / ((a + b) 4 pi delta^2 r) * [P(a) - P(b)] / (a - b),
    P(x) = -expm1(-x r) / x^2,

which is free of cancellation for small r, has the confluent limit
(4 tau^2 delta^2 = 1, a = b) as the derivative P'(a), and in the damped
oscillating case (4 tau^2 delta^2 > 1, a and b complex conjugates) reduces to
``Im P(a) / Im a``: the same real, positive-definite kernel, no special case
for the caller.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np

__all__ = [
    "Kernel",
    "MultiOrder",
    "ThinPlate",
    "Gaussian",
    "KERNELS",
    "make_kernel",
    "kernel_class",
    "register_kernel",
]

# Relative gap |a - b| / (a + b) below which the divided difference is
# replaced by the derivative at the midpoint (error ~ gap^2, ~1e-10).
_CONFLUENT_GAP = 1e-5
# a * r below which phi and phi'/r use their Taylor series at 0.
_SMALL_AR = 1e-3


class Kernel(ABC):
    """A radial basis function phi(r).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import Kernel, make_kernel
    >>> kernel = make_kernel('thinplate')
    >>> isinstance(kernel, Kernel), kernel(np.array([0.0, 2.0])).tolist(), kernel.polynomial_degree
    (True, [0.0, 8.0], 1)
    """

    name: str = ""
    polynomial_degree: int = 0
    positive_definite: bool = True

    @abstractmethod
    def __call__(self, r: np.ndarray) -> np.ndarray:
        """phi(r) for distances ``r >= 0``."""

    @abstractmethod
    def derivative(self, r: np.ndarray) -> np.ndarray:
        """d phi / d r."""

    @abstractmethod
    def derivative_over_r(self, r: np.ndarray) -> np.ndarray:
        """phi'(r) / r, with its finite limit phi''(0) at r = 0."""

    @property
    @abstractmethod
    def params(self) -> dict[str, float]:
        """The kernel's parameters, as keyword arguments of its constructor."""

    @property
    def value_at_zero(self) -> float:
        """phi(0)."""
        return float(self(np.zeros(1))[0])

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        """Names of the constructor's parameters (what ``make_kernel`` accepts)."""
        import inspect

        return tuple(n for n, p in inspect.signature(cls.__init__).parameters.items()
                     if n != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY))

    def to_dict(self) -> dict:
        """Name and parameters: ``make_kernel(**kernel.to_dict())`` rebuilds it."""
        return {"name": self.name, **self.params}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Kernel) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(tuple(sorted(self.to_dict().items())))


def _positive_finite(name: str, value: float, valid: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number ({valid}), got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be {valid}, got {value!r}")
    return value


class MultiOrder(Kernel):
    """The multi-order basis of Dinh, Turk & Slabaugh (2002).

    Parameters
    ----------
    delta : float
        Weight of the first-order (membrane) energy; enters squared.  Larger
        delta: shorter medium-range decay ``e^{-delta r}``, more local detail.
        Valid: ``0 < delta <= 1e4``.  Paper's range 5..40, typical 10.
    tau : float
        Weight of the third-order energy; the short range is about ``tau``.
        Valid: ``0 < tau <= 10``.  Paper's range 0.005..0.025, typical 0.01.

    Notes
    -----
    All three regimes of ``4 tau^2 delta^2`` (< 1 real decay rates, = 1
    confluent, > 1 damped oscillation) are supported; see the module notes.
    phi(0) = 1 / (4 pi delta sqrt(1 + 2 delta tau)), phi'(0) = 0, and far away
    phi ~ 1 / (4 pi delta^2 r).

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import MultiOrder
    >>> kernel = MultiOrder(delta=8, tau=0.02)
    >>> values = kernel(np.array([0.0, 0.1, 1.0]))
    >>> bool(values[0] == kernel.value_at_zero and values[0] > values[1] > values[2] > 0)  # decreasing, positive
    True
    """

    name = "multiorder"
    polynomial_degree = 0
    positive_definite = True

    def __init__(self, delta: float = 10.0, tau: float = 0.01):
        self.delta = _positive_finite("delta", delta, "a finite number in (0, 1e4]")
        self.tau = _positive_finite("tau", tau, "a finite number in (0, 10]")
        if self.delta > 1e4:
            raise ValueError(f"delta must be in (0, 1e4], got {delta!r}")
        if self.tau > 10:
            raise ValueError(f"tau must be in (0, 10], got {tau!r}")
        d, t = self.delta, self.tau
        disc = 1.0 - 4.0 * t * t * d * d
        sq = np.sqrt(complex(disc))
        v = (1.0 + sq) / (2.0 * t * t)
        w = (1.0 - sq) / (2.0 * t * t)
        a, b = np.sqrt(v), np.sqrt(w)
        self._a, self._b = complex(a), complex(b)
        self._c = 4.0 * math.pi * d * d
        # Symmetric functions of (a, b): always real.
        self._ab = d / t  # a*b = sqrt(v w) = delta / tau
        self._sum = math.sqrt(1.0 / (t * t) + 2.0 * d / t)  # a + b
        self._regime = "confluent" if abs(disc) <= 1e-12 else ("real" if disc > 0 else "complex")
        gap = abs(self._a - self._b) / self._sum
        self._confluent = gap < _CONFLUENT_GAP
        self._complex = (not self._confluent) and disc < 0
        # Decay rates, for callers that split the kernel (e.g. fast multipole).
        self.decay_rates = (self._a, self._b)
        self.coefficients = (
            (self._b**2 / (self._a**2 - self._b**2), -(self._a**2) / (self._a**2 - self._b**2))
            if not self._confluent
            else None
        )
        # Taylor coefficients D_n = A a^n + B b^n = (ab)^2 (a^{n-2} - b^{n-2}) / (a^2 - b^2)
        ab, s = self._ab, self._sum
        a2b2 = (self._a**2 + self._b**2).real  # a^2 + b^2 = v + w = 1/tau^2
        self._d1 = -ab / s
        self._d3 = ab * ab / s
        self._d4 = ab * ab
        self._d5 = ab * ab * (a2b2 + ab) / s

    @property
    def scale(self) -> float:
        """``4 pi delta^2``, the constant that divides the kernel's divided-difference form."""
        return self._c

    def series_coefficients(self) -> tuple[float, float, float, float]:
        """Taylor coefficients ``(D1, D3, D4, D5)`` of the kernel near ``r = 0``.

        ``D_n = A a^n + B b^n`` (always real), so that for small ``r``
        ``phi(r) ~ (-D1 - D3 r^2 / 6 + D4 r^3 / 24 - D5 r^4 / 120) / scale``.
        Compiled kernels (:mod:`o3drbf.rbf.compiled`) use the same series.

        Returns
        -------
        tuple of 4 floats
        """
        return self._d1, self._d3, self._d4, self._d5

    @property
    def regime(self) -> str:
        """``"real"``, ``"confluent"`` or ``"complex"`` (sign of 1 - 4 tau^2 delta^2)."""
        return self._regime

    @property
    def params(self) -> dict[str, float]:
        return {"delta": self.delta, "tau": self.tau}

    @property
    def value_at_zero(self) -> float:
        return 1.0 / (4.0 * math.pi * self.delta * math.sqrt(1.0 + 2.0 * self.delta * self.tau))

    # -- divided differences -------------------------------------------------
    def _divided(self, f, fprime, r):
        """[F(a) - F(b)] / (a - b) for F(x) = f(x, r), real-valued result."""
        a, b = self._a, self._b
        if self._confluent:
            m = 0.5 * self._sum  # (a + b) / 2, real
            return fprime(m, r)
        if self._complex:
            return f(a, r).imag / a.imag
        a, b = a.real, b.real
        return (f(a, r) - f(b, r)) / (a - b)

    def __call__(self, r):
        r = np.asarray(r, dtype=float)
        if self.coefficients is not None and self._regime == "real" and r.size > 64:
            # Fast path: phi = (1 + A e^{-ar} + B e^{-br}) / (C r); relative
            # error ~ 1e-16 / (b r), so entries with b r < 1e-3 are redone.
            (A, B), a, b = self.coefficients, self._a.real, self._b.real
            with np.errstate(divide="ignore", invalid="ignore"):
                out = np.exp(-a * r)
                out *= A.real
                tmp = np.exp(-b * r)
                tmp *= B.real
                out += tmp
                out += 1.0
                out /= r
                out /= self._c
            redo = r * b < 1e-3
            if redo.any():
                out[redo] = self._careful_value(r[redo])
            return out
        return self._careful_value(r)

    def _careful_value(self, r):
        out = np.empty_like(r)
        small = r * abs(self._a) < _SMALL_AR
        rs = r[small]
        # phi * C = -D1 + 0 r - D3 r^2 / 6 + D4 r^3 / 24 - D5 r^4 / 120
        out[small] = (-self._d1 - self._d3 * rs**2 / 6 + self._d4 * rs**3 / 24 - self._d5 * rs**4 / 120) / self._c
        rb = r[~small]
        if rb.size:

            def p(x, rr):
                return -np.expm1(-x * rr) / (x * x)

            def dp(x, rr):
                e = np.exp(-x * rr)
                return rr * e / (x * x) + 2.0 * np.expm1(-x * rr) / (x**3)

            dd = self._divided(p, dp, rb)
            out[~small] = -(self._ab**2) * dd / (self._sum * self._c * rb)
        return out

    def derivative_over_r(self, r):
        r = np.asarray(r, dtype=float)
        if self.coefficients is not None and self._regime == "real" and r.size > 64:
            # Fast path: phi'/r = -(1 + A e^{-ar}(1 + ar) + B e^{-br}(1 + br)) / (C r^3),
            # accurate where b r > 1e-2; the rest is redone carefully.
            (A, B), a, b = self.coefficients, self._a.real, self._b.real
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                out = np.exp(-a * r)
                out *= 1.0 + a * r
                out *= A.real
                tmp = np.exp(-b * r)
                tmp *= 1.0 + b * r
                tmp *= B.real
                out += tmp
                out += 1.0
                out /= -self._c * r**3
            redo = r * b < 1e-2
            if redo.any():
                out[redo] = self._careful_derivative_over_r(r[redo])
            return out
        return self._careful_derivative_over_r(r)

    def _careful_derivative_over_r(self, r):
        out = np.empty_like(r)
        small = r * abs(self._a) < _SMALL_AR
        rs = r[small]
        # phi'/r * C = sum_{n>=3} (-1)^n (n-1)/n! D_n r^{n-3}
        out[small] = (-2.0 / 6.0 * self._d3 + 3.0 / 24.0 * self._d4 * rs - 4.0 / 120.0 * self._d5 * rs**2) / self._c
        rb = r[~small]
        if rb.size:
            # phi' * C * r^2 = A q(ar) + B q(br), q(y) = 1 - e^{-y}(1 + y)
            #                = (ab)^2 [Q(a) - Q(b)] / ((a - b)(a + b)),  Q(x) = q(x r) / x^2
            def q(x, rr):
                y = x * rr
                return (-np.expm1(-y) - y * np.exp(-y)) / (x * x)

            def dq(x, rr):
                y = x * rr
                qy = -np.expm1(-y) - y * np.exp(-y)
                return rr * y * np.exp(-y) / (x * x) - 2.0 * qy / (x**3)

            dd = self._divided(q, dq, rb)
            out[~small] = (self._ab**2) * dd / (self._sum * self._c * rb**3)
        return out

    def derivative(self, r):
        r = np.asarray(r, dtype=float)
        return self.derivative_over_r(r) * r

    def fourier_symbol(self, k):
        """The 3-D Fourier transform of phi: 1 / (delta^2 k^2 + k^4 + tau^2 k^6)."""
        k2 = np.asarray(k, dtype=float) ** 2
        return 1.0 / (self.delta**2 * k2 + k2 * k2 + self.tau**2 * k2**3)


class ThinPlate(Kernel):
    """phi(r) = r^3 with a linear polynomial (Turk & O'Brien's variational implicits).

    Only conditionally positive definite (order 2): the system is solved as a
    symmetric indefinite saddle-point system.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import ThinPlate
    >>> ThinPlate()(np.array([1.0, 2.0])).tolist(), ThinPlate().positive_definite
    ([1.0, 8.0], False)
    """

    name = "thinplate"
    polynomial_degree = 1
    positive_definite = False

    def __call__(self, r):
        r = np.asarray(r, dtype=float)
        return r**3

    def derivative(self, r):
        r = np.asarray(r, dtype=float)
        return 3.0 * r**2

    def derivative_over_r(self, r):
        return 3.0 * np.asarray(r, dtype=float)

    @property
    def params(self) -> dict[str, float]:
        return {}


class Gaussian(Kernel):
    """phi(r) = exp(-(r / sigma)^2), with a constant polynomial.

    Parameters
    ----------
    sigma : float
        Width, in the normalized 2x2x2 box.  Valid: ``0 < sigma <= 100``.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import Gaussian
    >>> Gaussian(sigma=0.5)(np.array([0.0, 0.5])).round(4).tolist()
    [1.0, 0.3679]
    """

    name = "gaussian"
    polynomial_degree = 0
    positive_definite = True

    def __init__(self, sigma: float = 0.1):
        self.sigma = _positive_finite("sigma", sigma, "a finite number in (0, 100]")
        if self.sigma > 100:
            raise ValueError(f"sigma must be in (0, 100], got {sigma!r}")

    def __call__(self, r):
        r = np.asarray(r, dtype=float)
        return np.exp(-((r / self.sigma) ** 2))

    def derivative_over_r(self, r):
        r = np.asarray(r, dtype=float)
        return -2.0 / self.sigma**2 * np.exp(-((r / self.sigma) ** 2))

    def derivative(self, r):
        r = np.asarray(r, dtype=float)
        return self.derivative_over_r(r) * r

    def fourier_symbol(self, k):
        """pi^{3/2} sigma^3 exp(-(k sigma / 2)^2)."""
        k = np.asarray(k, dtype=float)
        return math.pi**1.5 * self.sigma**3 * np.exp(-((k * self.sigma / 2.0) ** 2))

    @property
    def params(self) -> dict[str, float]:
        return {"sigma": self.sigma}


#: name -> kernel class; the single source of truth for which kernels exist.
KERNELS: dict[str, type[Kernel]] = {
    MultiOrder.name: MultiOrder,
    ThinPlate.name: ThinPlate,
    Gaussian.name: Gaussian,
}


def register_kernel(cls: type[Kernel]) -> type[Kernel]:
    """Add a kernel class to :data:`KERNELS` (usable as a decorator).

    The class needs a unique ``name`` and the abstract methods of
    :class:`Kernel`; it then works everywhere a kernel name is accepted
    (``reconstruct(kernel=name)``, the command line's ``--kernel``, compare).
    Kernels without compiled or fast sums are evaluated by NumPy and solved
    densely.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf import KERNELS, Kernel, make_kernel, register_kernel
    >>> @register_kernel
    ... class Cubic(Kernel):
    ...     name, polynomial_degree, positive_definite = 'cubic_example', 1, False
    ...     def __call__(self, r): return np.asarray(r, float) ** 3
    ...     def derivative(self, r): return 3 * np.asarray(r, float) ** 2
    ...     def derivative_over_r(self, r): return 3 * np.asarray(r, float)
    ...     params = property(lambda self: {})
    >>> float(make_kernel('cubic_example')(2.0))
    8.0
    >>> _ = KERNELS.pop('cubic_example')  # registered for this example only
    """
    if not (isinstance(cls, type) and issubclass(cls, Kernel)) or not cls.name:
        raise ValueError("register_kernel takes a Kernel subclass with a name")
    key = cls.name.lower()
    if key in KERNELS and KERNELS[key] is not cls:
        raise ValueError(f"a kernel named {key!r} is already registered ({KERNELS[key].__name__})")
    KERNELS[key] = cls
    return cls


def kernel_class(name) -> type[Kernel]:
    """The registered kernel class for ``name`` (case, '-' and '_' ignored)."""
    if isinstance(name, Kernel):
        return type(name)
    key = str(name).lower().replace("-", "").replace("_", "")
    for k, cls in KERNELS.items():
        if k.replace("-", "").replace("_", "") == key:
            return cls
    raise ValueError(f"unknown kernel {name!r}; valid: {', '.join(KERNELS)}")


def make_kernel(name: str = "multiorder", **params: float) -> Kernel:
    """Build a kernel by name.

    Parameters
    ----------
    name : str or Kernel
        A key of :data:`KERNELS` ("multiorder", "thinplate", "gaussian", or
        one added by :func:`register_kernel`); a Kernel is returned as it is.
    **params
        The kernel's parameters (``delta``, ``tau`` for multiorder; ``sigma``
        for gaussian).  ``None`` values are dropped (use the default).

    Raises
    ------
    ValueError
        For an unknown name or a parameter the kernel does not take.

    Examples
    --------
    >>> from o3drbf import make_kernel
    >>> make_kernel('gaussian', sigma=0.2)
    Gaussian(sigma=0.2)
    >>> make_kernel('multiorder', delta=8, tau=0.02)
    MultiOrder(delta=8, tau=0.02)
    """
    if isinstance(name, Kernel):
        return name
    cls = kernel_class(name)
    params = {k: v for k, v in params.items() if v is not None}
    wrong = sorted(set(params) - set(cls.parameter_names()))
    if wrong:
        raise ValueError(f"kernel {cls.name!r} takes parameters {list(cls.parameter_names()) or 'none'}, got {sorted(params)}")
    return cls(**params)
