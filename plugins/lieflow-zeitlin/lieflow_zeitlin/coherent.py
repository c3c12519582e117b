r"""Coherent vortex structures of a vorticity field on the sphere: how many large-scale
vortices, their signs, positions and strengths.

The detector (:class:`VortexDetector`) works in three stages, every one of them invariant
under rotations of the sphere (up to the sampling of the point set):

1. **Low-pass.** The field ``ω = Q^{-1}(W)`` is smoothed by the heat kernel,
   ``ω̄_lm = exp(-σ² l(l+1)/2) ω_lm`` (for small ``σ`` a Gaussian of angular width ``σ``,
   radians), which keeps the large scales and removes the filaments and small vortices that
   an inviscid run keeps forever.
2. **Samples.** ``ω̄`` is evaluated at ``n`` quasi-uniform points (a Fibonacci lattice, each
   point standing for the area ``4π/n``), connected by their spherical Delaunay
   triangulation (the convex hull of the points).
3. **Persistence.** The positive part of ``ω̄`` and, separately, the positive part of
   ``-ω̄`` are swept from the top down (a union–find over the triangulation): each local
   maximum starts a component, and where two components meet (a saddle at level ``s``) the
   one with the lower peak dies, with persistence ``peak - s``; components still alive at
   the zero contour die there (persistence = peak). A maximum is a **coherent vortex** when
   its persistence is at least ``threshold · max|ω̄|``: weak bumps on the flank of a vortex
   and small-scale noise are merged into their neighbours, while two vortices separated by
   a deep saddle — or by the zero contour — stay two.

Each vortex's **basin** is the set of its sign's points that drain into it by steepest
ascent (through the insignificant maxima they merged with); its **circulation** is
``∫_basin ω̄ dΩ`` (the sum over the basin times ``4π/n``), its **position** the
``ω̄``-weighted centroid of the basin points above half the peak, projected onto the sphere
(finer than the point spacing), its **peak** the largest ``|ω̄|`` in it.

The persistence criterion is the standard one of topological data analysis (Edelsbrunner,
Letscher & Zomorodian 2002); applied to the low-passed vorticity it counts what
Modin & Viviani (2020) count by eye in their late-time snapshots: the 2, 3 or 4 "blobs".
"""

from __future__ import annotations

import math
from typing import Any

import attrs
import numpy as np
from numpy.typing import ArrayLike, NDArray

import lieflow

from .laplacian import matrix_size
from .quantization import matrix_to_sh

Array = NDArray[Any]

__all__ = ["Vortex", "VortexCensus", "VortexDetector", "fibonacci_points", "low_pass"]


def fibonacci_points(n: int) -> Array:
    """``n`` quasi-uniform unit vectors (the Fibonacci lattice, shape ``(n, 3)``):
    ``z_k = 1 - (2k + 1)/n``, longitude ``k · π(3 - √5)``; each stands for the area ``4π/n``."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 12:
        raise lieflow.InputError(f"the number of points must be an integer >= 12, got {n!r}")
    k = np.arange(n)
    z = 1.0 - (2 * k + 1) / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def low_pass(W: ArrayLike, smoothing: float) -> Array:
    """The matrix ``Q(ω̄)`` of the low-passed vorticity ``ω̄_lm = exp(-σ² l(l+1)/2) ω_lm``
    (``σ = smoothing``, radians) of the states ``W`` (shape ``(..., N, N)``): the field the
    detector looks at, as a matrix (for pictures)."""
    from .dissipation import degree_multiplier

    W = np.asarray(W)
    if W.ndim < 2 or W.shape[-1] != W.shape[-2]:
        raise lieflow.InputError(f"W must have shape (..., N, N), got {W.shape}")
    l = np.arange(W.shape[-1])
    return degree_multiplier(W, np.exp(-0.5 * smoothing**2 * l * (l + 1)))


@attrs.frozen
class Vortex:
    """One coherent vortex of a :class:`VortexCensus`.

    Attributes
    ----------
    sign : int
        ``+1`` (positive vorticity, counter-clockwise seen from outside) or ``-1``.
    position : tuple of float
        Unit vector of its centre.
    peak : float
        Largest ``|ω̄|`` in it (low-passed vorticity).
    circulation : float
        ``∫ ω̄ dΩ`` over its basin (signed).
    area : float
        Area of its basin (steradians).
    persistence : float
        ``peak`` minus the level at which it meets a stronger vortex of its sign (or ``peak``
        if it only meets the zero contour).
    """

    sign: int
    position: tuple[float, float, float]
    peak: float
    circulation: float
    area: float
    persistence: float

    @property
    def lat(self) -> float:
        """Latitude of the centre, degrees."""
        return math.degrees(math.asin(max(-1.0, min(1.0, self.position[2]))))

    @property
    def lon(self) -> float:
        """Longitude of the centre, degrees in ``[0, 360)``."""
        return math.degrees(math.atan2(self.position[1], self.position[0])) % 360.0


@attrs.frozen
class VortexCensus:
    """The coherent vortices of one state, strongest (largest ``|circulation|``) first.

    Attributes
    ----------
    vortices : tuple of Vortex
    amplitude : float
        ``max |ω̄|`` of the low-passed field (the scale of ``threshold``).
    """

    vortices: tuple[Vortex, ...]
    amplitude: float

    @property
    def count(self) -> int:
        """Number of coherent vortices."""
        return len(self.vortices)

    @property
    def positive(self) -> int:
        """Number of positive vortices."""
        return sum(v.sign > 0 for v in self.vortices)

    @property
    def negative(self) -> int:
        """Number of negative vortices."""
        return sum(v.sign < 0 for v in self.vortices)


def _positive_float(name: str) -> Any:
    def check(_inst: object, _attr: attrs.Attribute, value: float) -> None:
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise lieflow.InputError(f"{name} must be a finite positive number, got {value!r}")

    return check


def _fraction(_inst: object, _attr: attrs.Attribute, value: float) -> None:
    if not (isinstance(value, (int, float)) and 0 < value < 1):
        raise lieflow.InputError(f"threshold must be a number in (0, 1), got {value!r}")


def _default_points(self: VortexDetector) -> int:
    """A spacing of a quarter of the low-pass width: ``4π (4/σ)²`` points, 1500 to 20 000."""
    s = self.smoothing
    if not (isinstance(s, (int, float)) and math.isfinite(s) and s > 0):
        return 1500  # the validator refuses this smoothing
    return int(np.clip(4 * math.pi * (4 / s) ** 2, 1500, 20_000))


def _basis(N: int, points: Array, smoothing: float) -> tuple[Array, Array]:
    r"""Real matrix ``E`` with ``ω̄(x_p) = E[p] @ [Re ω_lm, Im ω_lm]`` over ``m >= 0``
    (``ω_l0 Y_l0 + 2 Re Σ_{m>0} ω_lm Y_lm``), the heat-kernel factors folded in; degrees whose
    factor is below ``1e-9`` are left out."""
    from scipy.special import sph_harm_y  # 0.1 s to import: on first use

    theta = np.arccos(np.clip(points[:, 2], -1.0, 1.0))
    phi = np.arctan2(points[:, 1], points[:, 0])
    columns = []
    index = []
    for l in range(1, N):
        factor = math.exp(-0.5 * smoothing**2 * l * (l + 1))
        if factor < 1e-9:
            break
        for m in range(l + 1):
            Y = sph_harm_y(l, m, theta, phi) * factor
            k = l * (l + 1) + m
            if m == 0:
                columns.append(Y.real)
                index.append((k, 0))
            else:
                columns += [2 * Y.real, -2 * Y.imag]
                index += [(k, 0), (k, 1)]
    E = np.stack(columns, axis=-1) if columns else np.zeros((len(points), 0))
    E.setflags(write=False)
    where = np.array(index, dtype=np.intp).reshape(-1, 2)
    where.setflags(write=False)
    return E, where


def _edges(points: Array) -> tuple[Array, Array]:
    """Neighbours in the spherical Delaunay triangulation (convex hull) as CSR arrays."""
    from scipy.spatial import ConvexHull

    tri = ConvexHull(points).simplices
    a = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2], tri[:, 1], tri[:, 2], tri[:, 0]])
    b = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0], tri[:, 0], tri[:, 1], tri[:, 2]])
    pairs = np.unique(np.stack([a, b], axis=-1), axis=0)
    start = np.searchsorted(pairs[:, 0], np.arange(len(points) + 1))
    start.setflags(write=False)
    nbr = pairs[:, 1].copy()
    nbr.setflags(write=False)
    return start, nbr


@attrs.frozen(eq=False)
class VortexDetector:
    """Counts the coherent vortices of su(N) vorticity states (module docs for the method).

    Parameters
    ----------
    N : int
        Matrix size of the states.
    smoothing : float
        Width ``σ`` (radians) of the heat-kernel low-pass, default 0.3 (17°): vortices much
        smaller than this are not "coherent structures" of the large scale.
    threshold : float
        Smallest persistence of a vortex, as a fraction of ``max|ω̄|`` (default 0.2).
    points : int
        Number of sample points (spacing ``√(4π/n)``; default ``4π(4/σ)²``, a quarter of
        the low-pass width, between 1500 and 20 000: the low-passed field varies on the
        scale ``σ``, whatever ``N``).

    The sample points, their triangulation and the synthesis matrix are built once, here
    (read-only arrays); :meth:`census` is then one transform ``W -> ω_lm`` (O(N³)), one
    matrix–vector product and one sweep over the points.
    """

    N: int = attrs.field(converter=matrix_size)
    smoothing: float = attrs.field(default=0.3, validator=_positive_float("smoothing"))
    threshold: float = attrs.field(default=0.2, validator=_fraction)
    points: int = attrs.field(default=attrs.Factory(_default_points, takes_self=True))
    xyz: Array = attrs.field(init=False, repr=False)
    _synthesis: tuple[Array, Array] = attrs.field(init=False, repr=False)
    _graph: tuple[Array, Array] = attrs.field(init=False, repr=False)

    @xyz.default
    def _xyz(self) -> Array:
        p = fibonacci_points(self.points)
        p.setflags(write=False)
        return p

    @_synthesis.default
    def _synthesis_default(self) -> tuple[Array, Array]:
        return _basis(self.N, self.xyz, self.smoothing)

    @_graph.default
    def _graph_default(self) -> tuple[Array, Array]:
        return _edges(self.xyz)

    def _states(self, W: ArrayLike) -> Array:
        W = np.asarray(W)
        if W.ndim < 2 or W.shape[-2:] != (self.N, self.N):
            raise lieflow.InputError(
                f"W has shape {W.shape}; this detector is for (..., {self.N}, {self.N})"
            )
        return W

    def filtered(self, W: ArrayLike) -> Array:
        """The low-passed vorticity ``ω̄`` at the sample points :attr:`xyz`, shape
        ``(..., points)``."""
        coeffs = matrix_to_sh(self._states(W))
        E, index = self._synthesis
        parts = np.stack([coeffs.real, coeffs.imag], axis=-1)[..., index[:, 0], index[:, 1]]
        return np.asarray(parts @ E.T)

    def census(self, W: ArrayLike) -> VortexCensus:
        """The coherent vortices of one state ``W`` (shape ``(N, N)``)."""
        W = np.asarray(W)
        if W.ndim != 2:
            raise lieflow.InputError(
                f"census takes one state of shape ({self.N}, {self.N}), got {W.shape}; "
                "loop over a stack"
            )
        return self.census_of_field(self.filtered(W))

    def census_of_field(self, values: ArrayLike) -> VortexCensus:
        """The coherent vortices of a low-passed field given by its ``values`` at the
        sample points :attr:`xyz` (as :meth:`filtered` returns)."""
        f = np.asarray(values, dtype=float)
        if f.shape != (self.points,):
            raise lieflow.InputError(
                f"values must have shape ({self.points},) (one per sample point), got {f.shape}"
            )
        amplitude = float(np.max(np.abs(f))) if f.size else 0.0
        if not amplitude > 0:
            return VortexCensus((), 0.0)
        found = [*self._sweep(f, +1, amplitude), *self._sweep(-f, -1, amplitude)]
        found.sort(key=lambda v: -abs(v.circulation))
        return VortexCensus(tuple(found), amplitude)

    def _sweep(self, g: Array, sign: int, amplitude: float) -> list[Vortex]:
        """Vortices of the positive part of ``g`` (``sign`` says which sign of ``ω̄`` that is).

        Steepest ascent (each point to its highest neighbour, resolved by pointer jumping)
        gives every positive point the maximum it drains into; the basins' 0-dimensional
        persistence is then Kruskal's algorithm on the basin graph, the edges taken by
        decreasing saddle level ``min(g_u, g_v)`` with the elder rule (an edge inside a basin
        never joins two components: both ends already reach its peak through higher points).
        """
        start, nbr = self._graph
        src = np.repeat(np.arange(g.size), np.diff(start))
        rank = np.empty(g.size, dtype=np.intp)  # a strict order: g, then the index
        rank[np.lexsort((np.arange(g.size), g))] = np.arange(g.size)
        first = np.lexsort((-rank[nbr], src))[start[:-1]]  # each point's highest neighbour
        up = np.where(rank[nbr[first]] > rank, nbr[first], np.arange(g.size))
        drain = up
        while True:
            nxt = drain[drain]
            if np.array_equal(nxt, drain):
                break
            drain = nxt
        positive = g > 0
        cross = positive[src] & positive[nbr] & (drain[src] < drain[nbr])
        a, b = drain[src[cross]], drain[nbr[cross]]
        level = np.minimum(g[src[cross]], g[nbr[cross]])
        peaks = np.flatnonzero(positive & (drain == np.arange(g.size)))
        root = {int(p): int(p) for p in peaks}
        merged_into: dict[int, int] = {}
        persistence: dict[int, float] = {}

        def find(i: int) -> int:
            while root[i] != i:
                root[i] = root[root[i]]
                i = root[i]
            return i

        for k in np.argsort(-level, kind="stable").tolist():
            ra, rb = find(int(a[k])), find(int(b[k]))
            if ra == rb:
                continue
            high, low = (ra, rb) if g[ra] >= g[rb] else (rb, ra)
            persistence[low] = float(g[low] - level[k])  # the lower peak dies here
            merged_into[low] = high
            root[low] = high
        for p in root:
            if p not in persistence:  # alive down to the zero contour
                persistence[p] = float(g[p])
        keep = {p for p, pers in persistence.items() if pers >= self.threshold * amplitude}
        owner = np.full(g.size, -1)
        for p in root:
            q = p
            while q not in keep and q in merged_into:
                q = merged_into[q]
            owner[p] = q if q in keep else -1
        label = np.where(positive, owner[drain], -1)
        cell = 4 * math.pi / g.size
        out = []
        for peak in sorted(keep, key=lambda q: -g[q]):
            members = np.flatnonzero(label == peak)
            core = members[g[members] >= 0.5 * g[peak]]
            centre = (g[core, None] * self.xyz[core]).sum(axis=0)
            centre /= np.linalg.norm(centre)
            out.append(
                Vortex(
                    sign=sign,
                    position=(float(centre[0]), float(centre[1]), float(centre[2])),
                    peak=float(g[peak]),
                    circulation=sign * float(g[members].sum()) * cell,
                    area=members.size * cell,
                    persistence=persistence[peak],
                )
            )
        return out
