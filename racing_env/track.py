"""Race tracks in the Frenet frame of their centreline.

A :class:`Track` stores the centreline sampled on a uniform arc-length grid: curvature,
left/right widths and, for drawing, the Cartesian centreline. Conventions:

* ``s`` is arc length along the centreline [m]; ``n`` is the lateral offset [m], positive to
  the LEFT of the driving direction.
* ``kappa`` [1/m] is positive for LEFT (counter-clockwise) turns.
* Closed tracks wrap ``s`` modulo ``length``; open tracks (straights) clamp lookups to
  ``[0, length]``.

The lookups (:meth:`Track.kappa_at`, :meth:`Track.wrap_s`, ...) are written in ``jax.numpy``
and work under ``jit``/``vmap``/``grad``; a ``Track`` is a pytree, so it can be passed into
jitted functions (its arrays become leaves, ``length``/``closed``/``name`` are static). The
Cartesian conversions are NumPy helpers for drawing and analysis.

Builders: :func:`straight`, :func:`from_centerline` (smoothing-spline fit of a measured
centreline), :func:`from_csv` (TUMFTM racetrack-database files), :func:`trefoil`,
:func:`random_circuit`, the shipped real circuits of the TUMFTM racetrack-database
(:func:`circuit`, :func:`circuit_names`, :func:`raceline_path`), and :func:`get_track` to
resolve names and paths.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.vehicle import is_concrete

ArrayLike = float | np.ndarray | jax.Array

#: Default positional noise [m] assumed by :func:`from_centerline` / :func:`from_csv`.
DEFAULT_SMOOTHING = 0.3

_ARRAY_FIELDS = ("s", "kappa", "width_left", "width_right", "x", "y", "heading")
_MIN_GRID_POINTS = 4
_MIN_CENTERLINE_POINTS = 10


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles [rad] into [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _as_float(a: ArrayLike) -> jax.Array:
    """``a`` as a JAX floating array (integers promoted to the default float dtype)."""
    a = jnp.asarray(a)
    if not jnp.issubdtype(a.dtype, jnp.floating):
        a = a.astype(jnp.result_type(float))
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class Track:
    """A track sampled on a uniform arc-length grid of ``M`` points.

    Attributes:
        s: ``(M,)`` arc-length grid [m], ``s[k] = k * ds``. Closed tracks do not repeat the
            end point (``s[-1] = length - ds``); open tracks end at ``s[-1] = length``.
        kappa: ``(M,)`` centreline curvature [1/m], positive for left turns.
        width_left: ``(M,)`` distance from the centreline to the left boundary [m], > 0.
        width_right: ``(M,)`` distance from the centreline to the right boundary [m], > 0.
        x: ``(M,)`` centreline x coordinate [m].
        y: ``(M,)`` centreline y coordinate [m].
        heading: ``(M,)`` centreline tangent angle [rad], unwrapped (continuous).
        length: total centreline length [m] (static).
        closed: whether the track is a loop (static).
        name: display name (static).
        scale: the factor this track is a model of the circuit ``name`` at (static): 1 at
            full size, 0.1 for a 1:10 model (:func:`scaled`); its racing line is the full-size
            circuit's, scaled alike.
    """

    s: np.ndarray
    kappa: np.ndarray
    width_left: np.ndarray
    width_right: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    length: float
    closed: bool
    name: str = "track"
    scale: float = 1.0

    def __post_init__(self) -> None:
        arrays = {f: getattr(self, f) for f in _ARRAY_FIELDS}
        # Unflattening inside jit/vmap rebuilds the Track from tracers (or other leaf
        # types); those were validated when the concrete Track was built. Concrete JAX
        # arrays are checked and copied like NumPy ones.
        if not all(isinstance(a, (np.ndarray, jax.Array)) and is_concrete(a) for a in arrays.values()):
            return
        arrays = {f: np.asarray(a) for f, a in arrays.items()}
        if not (np.isfinite(self.length) and self.length > 0):
            raise ValueError(f"Track.length must be finite and > 0 [m], got {self.length!r}")
        shape = arrays["s"].shape
        for field, a in arrays.items():
            if a.ndim != 1 or a.shape != shape:
                raise ValueError(
                    f"Track.{field} must be 1-D with the same shape as Track.s {shape}, "
                    f"got shape {a.shape}"
                )
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Track.{field} must be finite everywhere")
        m = shape[0]
        if m < _MIN_GRID_POINTS:
            raise ValueError(f"Track needs at least {_MIN_GRID_POINTS} grid points, got {m}")
        for field in ("width_left", "width_right"):
            if np.any(arrays[field] <= 0):
                raise ValueError(
                    f"Track.{field} must be > 0 [m] everywhere, min is {arrays[field].min():g}"
                )
        ds = self.length / (m if self.closed else m - 1)
        if not np.allclose(arrays["s"], ds * np.arange(m), rtol=0.0, atol=1e-6 * self.length):
            raise ValueError(
                "Track.s must be the uniform grid k * ds with ds = length / M (closed) or "
                f"length / (M - 1) (open); expected ds={ds:g} for length={self.length:g}, M={m}"
            )
        # Own read-only float64 copies: the Track is immutable and shared between agents.
        for field, a in arrays.items():
            a = np.array(a, dtype=np.float64)
            a.flags.writeable = False
            object.__setattr__(self, field, a)
        object.__setattr__(self, "length", float(self.length))
        object.__setattr__(self, "closed", bool(self.closed))

    # ----------------------------------------------------------------------------------
    # Grid properties (static: derived from meta data and array shapes, valid under jit).

    @property
    def num_points(self) -> int:
        """Number of grid points ``M``."""
        return self.s.shape[0]

    @property
    def ds(self) -> float:
        """Grid spacing [m]."""
        m = self.num_points
        return self.length / (m if self.closed else m - 1)

    def __repr__(self) -> str:
        return (
            f"Track(name={self.name!r}, length={self.length:.1f} m, "
            f"closed={self.closed}, M={self.num_points})"
        )

    # ----------------------------------------------------------------------------------
    # JAX lookups.

    def wrap_s(self, s: ArrayLike) -> jax.Array:
        """Arc length mapped onto the track [m]: ``s mod length`` in ``[0, length)`` for
        closed tracks, clipped to ``[0, length]`` for open ones. Same shape as ``s``."""
        s = _as_float(s)
        if not self.closed:
            return jnp.clip(s, 0.0, self.length)
        r = jnp.mod(s, self.length)
        # Floating-point mod can return exactly `length` for tiny negative s.
        return jnp.where(r >= self.length, r - self.length, r)

    def wrap_ds(self, ds: ArrayLike) -> jax.Array:
        """Signed arc-length difference [m] (e.g. the gap ``s_other - s_ego``), wrapped into
        ``[-length/2, length/2)`` on closed tracks; unchanged on open ones."""
        ds = _as_float(ds)
        if not self.closed:
            return ds
        half = 0.5 * self.length
        r = jnp.mod(ds + half, self.length)
        r = jnp.where(r >= self.length, r - self.length, r)
        return r - half

    def wrap_ds_in(self, ds, xp=np):
        """:meth:`wrap_ds` in the array module ``xp``: in NumPy (``np``, the default) the same
        operations on the host, without a device dispatch; ``jax.numpy`` under ``jit``. For
        code that runs in the agents' host loops and inside compiled races alike."""
        if not self.closed:
            return ds
        length = float(self.length)
        r = xp.mod(ds + 0.5 * length, length)
        return xp.where(r >= length, r - length, r) - 0.5 * length

    def _interp(self, values: ArrayLike, s: ArrayLike) -> jax.Array:
        """Piecewise-linear interpolation of grid ``values`` (M,) at ``s`` (any shape)."""
        values = jnp.asarray(values)
        m = values.shape[0]
        u = self.wrap_s(s) / self.ds  # fractional grid index
        if self.closed:
            i0 = jnp.floor(u)
            frac = u - i0
            i0 = i0.astype(jnp.int32) % m  # u == m can occur through rounding
            i1 = (i0 + 1) % m
        else:
            i0 = jnp.clip(jnp.floor(u), 0, m - 2)  # s == length uses the last segment
            frac = u - i0
            i0 = i0.astype(jnp.int32)
            i1 = i0 + 1
        return (1.0 - frac) * values[i0] + frac * values[i1]

    def kappa_at(self, s: ArrayLike) -> jax.Array:
        """Centreline curvature [1/m] at arc length ``s`` [m]; same shape as ``s``."""
        return self._interp(self.kappa, s)

    def width_left_at(self, s: ArrayLike) -> jax.Array:
        """Distance from the centreline to the left boundary [m] at ``s``; shape of ``s``."""
        return self._interp(self.width_left, s)

    def width_right_at(self, s: ArrayLike) -> jax.Array:
        """Distance from the centreline to the right boundary [m] at ``s``; shape of ``s``."""
        return self._interp(self.width_right, s)

    # ----------------------------------------------------------------------------------
    # NumPy geometry for drawing.
    #
    # The Frenet <-> Cartesian map is defined on the sampled centreline itself: between
    # grid points k and k+1 a point (s, n) is the linear blend of the offset points
    # C_k + n N_k and C_{k+1} + n N_{k+1} (N = unit left normal from the fitted heading).
    # This is exactly invertible (a quadratic per segment), so to_cartesian and
    # from_cartesian round-trip to rounding error for |n| below the radius of curvature,
    # and boundaries() lies exactly at n = width_left / -width_right.

    def _vertices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grid points ``(K, 2)``, unit left normals ``(K, 2)`` and headings ``(K,)`` with
        ``K = M + 1`` for closed tracks (first point appended, heading continued) and
        ``K = M`` for open ones, so that segment ``k`` always joins rows ``k`` and ``k+1``."""
        xy = np.stack([np.asarray(self.x), np.asarray(self.y)], axis=-1)
        heading = np.asarray(self.heading, dtype=np.float64)
        if self.closed:
            xy = np.concatenate([xy, xy[:1]])
            closing = heading[-1] + _wrap_angle(heading[0] - heading[-1])
            heading = np.append(heading, closing)
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        return xy, normal, heading

    def _segment(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segment index, fraction in [0, 1] and wrapped s for arc lengths ``s``."""
        s = np.asarray(s, dtype=np.float64)
        if self.closed:
            s = np.mod(s, self.length)
        else:
            s = np.clip(s, 0.0, self.length)
        num_segments = self.num_points if self.closed else self.num_points - 1
        u = s / self.ds
        k = np.clip(np.floor(u), 0, num_segments - 1).astype(np.int64)
        return k, np.clip(u - k, 0.0, 1.0), s

    def to_cartesian(
        self, s: ArrayLike, n: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frenet ``(s, n)`` [m] to Cartesian ``(x, y, heading)`` [m, m, rad].

        ``s`` and ``n`` broadcast against each other. The point is the centreline point at
        ``s`` offset by ``n`` along the left normal; ``heading`` is the centreline heading at
        ``s`` (add the car's relative heading chi for the car's yaw).
        """
        s, n = np.broadcast_arrays(np.asarray(s, np.float64), np.asarray(n, np.float64))
        xy, normal, heading = self._vertices()
        k, t, _ = self._segment(s)
        t_ = t[..., None]
        n_ = n[..., None]
        p0 = xy[k] + n_ * normal[k]
        p1 = xy[k + 1] + n_ * normal[k + 1]
        p = (1.0 - t_) * p0 + t_ * p1
        h = (1.0 - t) * heading[k] + t * heading[k + 1]
        return p[..., 0], p[..., 1], h

    def from_cartesian(self, x: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Cartesian ``(x, y)`` [m] to Frenet ``(s, n)`` [m], the inverse of
        :meth:`to_cartesian` (broadcasting ``x`` against ``y``).

        Exact (to rounding) for points within a radius of curvature of the centreline; ``s``
        is in ``[0, length)`` (closed) or ``[0, length]`` (open, points beyond the ends get
        the end's ``s`` and their offset from the extended end segment). Points far away
        from the track fall back to the nearest point on the centreline polyline.
        """
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        shape = x.shape
        p = np.stack([x.ravel(), y.ravel()], axis=-1)  # (P, 2)
        xy, normal, _ = self._vertices()
        m = self.num_points
        num_segments = m if self.closed else m - 1

        # Candidate segments: a window around each of a few nearest grid points (several,
        # so a point on one leg of a hairpin cannot be captured by the other leg).
        k_nn = min(4, m)
        from scipy import spatial  # imported on use: SciPy would slow down `import racing_env`

        _, nearest = spatial.cKDTree(xy[:m]).query(p, k=k_nn)
        nearest = nearest.reshape(len(p), k_nn)
        window = np.arange(-3, 3)
        seg = (nearest[:, :, None] + window).reshape(len(p), -1)  # (P, C)
        seg = seg % m if self.closed else np.clip(seg, 0, num_segments - 1)

        a0, b = xy[seg], xy[seg + 1] - xy[seg]  # segment start and chord, (P, C, 2)
        n0, dn = normal[seg], normal[seg + 1] - normal[seg]
        q = p[:, None, :] - a0

        def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

        # q = t b + n (n0 + t dn)  <=>  (q - t b) x (n0 + t dn) = 0, a quadratic in t.
        qa = -cross(b, dn)
        qb = cross(q, dn) - cross(b, n0)
        qc = cross(q, n0)
        with np.errstate(all="ignore"):
            disc = qb**2 - 4.0 * qa * qc
            root = -0.5 * (qb + np.where(qb >= 0, 1.0, -1.0) * np.sqrt(disc))
            ts = np.stack([root / qa, qc / root], axis=-1)  # stable pair; qa=0 -> linear
            nrm = n0[..., None, :] + ts[..., None] * dn[..., None, :]
            ns = np.sum((q[..., None, :] - ts[..., None] * b[..., None, :]) * nrm, -1)
            ns = ns / np.sum(nrm**2, axis=-1)
        eps = 1e-9
        lo_ok = ts >= -eps
        hi_ok = ts <= 1.0 + eps
        if not self.closed:  # extend the end segments beyond the ends of open tracks
            lo_ok |= (seg == 0)[..., None]
            hi_ok |= (seg == num_segments - 1)[..., None]
        valid = np.isfinite(ts) & np.isfinite(ns) & (disc >= 0)[..., None] & lo_ok & hi_ok
        score = np.where(valid, np.abs(ns), np.inf).reshape(len(p), -1)
        best = np.argmin(score, axis=1)
        rows = np.arange(len(p))
        found = np.isfinite(score[rows, best])
        best_seg = seg[rows, best // 2]
        t = ts.reshape(len(p), -1)[rows, best]
        n = ns.reshape(len(p), -1)[rows, best]

        if not np.all(found):  # far from the track: nearest point of the polyline
            bb = np.sum(b**2, axis=-1)
            tp = np.clip(np.sum(q * b, axis=-1) / bb, 0.0, 1.0)
            foot = q - tp[..., None] * b
            dist = np.hypot(foot[..., 0], foot[..., 1])
            j = np.argmin(dist, axis=1)
            side = np.sign(cross(b[rows, j], foot[rows, j]))
            best_seg = np.where(found, best_seg, seg[rows, j])
            t = np.where(found, t, tp[rows, j])
            n = np.where(found, n, side * dist[rows, j])

        s = (best_seg + t) * self.ds
        s = np.clip(s, 0.0, self.length) if not self.closed else np.mod(s, self.length)
        if self.closed:
            s = np.where(s >= self.length, s - self.length, s)
        return s.reshape(shape), n.reshape(shape)

    def boundaries(self) -> tuple[np.ndarray, np.ndarray]:
        """Left and right track boundaries at the grid points, each ``(M, 2)`` [m]."""
        xy, normal, _ = self._vertices()
        xy, normal = xy[: self.num_points], normal[: self.num_points]
        left = xy + np.asarray(self.width_left)[:, None] * normal
        right = xy - np.asarray(self.width_right)[:, None] * normal
        return left, right


jax.tree_util.register_dataclass(
    Track, data_fields=list(_ARRAY_FIELDS), meta_fields=["length", "closed", "name", "scale"]
)


def check_scale(scale: float) -> float:
    """``scale`` as a float, refused unless a finite number > 0 (1: full size, 0.1: a 1:10 model)."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.number)) or not (
            np.isfinite(scale) and scale > 0):
        raise ValueError(f"a track's scale must be a finite number > 0 (1: full size, 0.1: a 1:10 model), got {scale!r}")
    return float(scale)


def scaled(track: Track, scale: float) -> Track:
    """``track`` as a model at ``scale`` (> 0): every length times ``scale`` (the grid, the
    widths, the centre line's points), the curvature over it, the headings as they are; an
    exact geometric copy, so a car whose speeds are ``sqrt(scale)`` times another's at the same
    accelerations laps it in ``sqrt(scale)`` times the time.

    Raises:
        ValueError: for a scale that is not a finite number > 0.
    """
    scale = check_scale(scale)
    if scale == 1.0:
        return track
    arrays = {f: np.asarray(getattr(track, f)) for f in _ARRAY_FIELDS}
    for f in ("s", "width_left", "width_right", "x", "y"):
        arrays[f] = arrays[f] * scale
    arrays["kappa"] = arrays["kappa"] / scale
    return Track(**arrays, length=track.length * scale, closed=track.closed, name=track.name,
                 scale=track.scale * scale)


# --------------------------------------------------------------------------------------
# Builders.


def straight(
    length: float = 300.0,
    width_left: float = 6.0,
    width_right: float = 6.0,
    ds: float = 1.0,
    name: str = "straight",
) -> Track:
    """An open straight along +x starting at the origin.

    Args:
        length: length [m].
        width_left, width_right: constant widths [m].
        ds: requested grid spacing [m]; the actual one is ``length / round(length / ds)``.
        name: display name.
    """
    if not (np.isfinite(ds) and ds > 0):
        raise ValueError(f"ds must be > 0 [m], got {ds!r}")
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"length must be > 0 [m], got {length!r}")
    m = max(_MIN_GRID_POINTS, int(round(length / ds)) + 1)
    s = np.linspace(0.0, length, m)
    zeros = np.zeros(m)
    return Track(
        s=s,
        kappa=zeros,
        width_left=np.full(m, float(width_left)),
        width_right=np.full(m, float(width_right)),
        x=s.copy(),
        y=zeros.copy(),
        heading=zeros.copy(),
        length=float(length),
        closed=False,
        name=name,
    )


def _clean_centerline(
    x: ArrayLike, y: ArrayLike, width_right: ArrayLike, width_left: ArrayLike, closed: bool
) -> tuple[np.ndarray, ...]:
    """Validate centreline samples; drop consecutive duplicates and a repeated end point."""
    arrays = [np.asarray(a, dtype=np.float64) for a in (x, y, width_right, width_left)]
    names = ("x", "y", "width_right", "width_left")
    for name, a in zip(names, arrays):
        if a.ndim != 1:
            raise ValueError(f"from_centerline: {name} must be 1-D, got shape {a.shape}")
    if len({a.shape[0] for a in arrays}) != 1:
        shapes = ", ".join(f"{nm}={a.shape[0]}" for nm, a in zip(names, arrays))
        raise ValueError(f"from_centerline: inputs must have equal lengths, got {shapes}")
    for name, a in zip(names, arrays):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"from_centerline: {name} must be finite")
    for name, a in zip(names[2:], arrays[2:]):
        if np.any(a <= 0):
            i = int(np.argmax(a <= 0))
            raise ValueError(
                f"from_centerline: {name} must be > 0 [m], got {a[i]:g} at point {i}"
            )
    x, y, wr, wl = arrays
    # Repeated points have no direction and break the spline parametrisation: drop them.
    keep = np.ones(x.shape[0], dtype=bool)
    keep[1:] = (np.diff(x) != 0) | (np.diff(y) != 0)
    x, y, wr, wl = (a[keep] for a in (x, y, wr, wl))
    if closed and x.shape[0] > 1 and x[-1] == x[0] and y[-1] == y[0]:
        x, y, wr, wl = (a[:-1] for a in (x, y, wr, wl))  # loop closed explicitly
    if x.shape[0] < _MIN_CENTERLINE_POINTS:
        raise ValueError(
            f"from_centerline: need at least {_MIN_CENTERLINE_POINTS} distinct centreline "
            f"points, got {x.shape[0]}"
        )
    return x, y, wr, wl


def _arc_length_table(
    tck: tuple, u_start: float, u_end: float, num_intervals: int
) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative arc length [m] of the spline at ``num_intervals + 1`` parameter edges,
    by 5-point Gauss-Legendre quadrature of ``|r'(u)|`` on each interval."""
    edges = np.linspace(u_start, u_end, num_intervals + 1)
    cum = np.concatenate([[0.0], np.cumsum(_arc_length_between(tck, edges[:-1], edges[1:]))])
    return edges, cum


def _arc_length_between(tck: tuple, u0: np.ndarray, u1: np.ndarray) -> np.ndarray:
    """Arc length [m] of the spline between parameters ``u0`` and ``u1`` (short spans)."""
    from scipy import interpolate
    nodes, weights = np.polynomial.legendre.leggauss(5)
    mid, half = 0.5 * (u0 + u1), 0.5 * (u1 - u0)
    uq = mid[:, None] + half[:, None] * nodes
    dx, dy = interpolate.splev(uq.ravel(), tck, der=1)
    speed = np.hypot(dx, dy).reshape(uq.shape)
    return half * (speed @ weights)


def from_centerline(
    x: ArrayLike,
    y: ArrayLike,
    width_right: ArrayLike,
    width_left: ArrayLike,
    closed: bool = True,
    ds: float = 1.0,
    smoothing: float = DEFAULT_SMOOTHING,
    name: str = "track",
) -> Track:
    """Build a track from (measured) centreline points, as in the TUMFTM database.

    The points are fitted with a cubic parametric smoothing spline (``splprep``; periodic
    when ``closed``), parametrised by chord length. ``smoothing`` is the assumed positional
    noise sigma [m] of the points: the fit may deviate from them by an RMS distance of up to
    sigma (FITPACK smoothing factor ``num_points * sigma**2``). Curvature is a second
    derivative, so even centimetre noise on 5 m spaced points shows up as curvature spikes
    of order ``noise / spacing**2``; the smoothing removes them. The default,
    ``DEFAULT_SMOOTHING = 0.3`` m, is the smallest value that removes the spurious
    double spikes (ringing) in the curvature at Monza's chicanes that remain at 0.1-0.2 m;
    it moves the centreline by 0.27 m RMS (at most ~1.8 m, at chicane apexes), well
    within the half-width. ``smoothing=0`` interpolates the points exactly: use it for
    analytic, noise-free curves. FITPACK uses as few knots as the tolerance allows, so with
    ``smoothing > 0`` the curvature along long constant-radius arcs ripples by ~10-20%
    around the true value (the mean, i.e. the total turning, is preserved).

    The spline is resampled at uniform true arc length (quadrature of ``|r'|``), with
    ``kappa = (x'y'' - y'x'') / |r'|^3``, ``heading = atan2(y', x')`` (unwrapped), and the
    widths interpolated linearly in arc length (periodically for closed tracks).

    Args:
        x, y: ``(P,)`` centreline points [m], in driving order. For closed tracks the loop
            is closed implicitly (if the last point repeats the first, it is dropped).
        width_right, width_left: ``(P,)`` distances to the right/left boundary [m], > 0.
        closed: whether the centreline is a loop.
        ds: requested grid spacing [m]; the actual one divides the length evenly
            (``Track.ds``).
        smoothing: assumed positional noise sigma [m], >= 0.
        name: display name.

    Raises:
        ValueError: for fewer than 10 distinct points, unequal lengths, non-finite values,
            non-positive widths, or bad ``ds``/``smoothing``. Exact consecutive duplicate
            points are removed silently (keeping the first).
    """
    if not (np.isfinite(ds) and ds > 0):
        raise ValueError(f"from_centerline: ds must be > 0 [m], got {ds!r}")
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise ValueError(f"from_centerline: smoothing must be >= 0 [m], got {smoothing!r}")
    from scipy import interpolate

    x, y, wr, wl = _clean_centerline(x, y, width_right, width_left, closed)
    num_in = x.shape[0]

    # Chord-length parameter u [m] (|r'| ~ 1); a periodic fit needs the first point
    # repeated at the end (its value is ignored, it only sets the period).
    if closed:
        xs, ys = np.append(x, x[0]), np.append(y, y[0])
    else:
        xs, ys = x, y
    u = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(ys)))])
    tck, _ = interpolate.splprep(
        [xs, ys], u=u, k=3, s=num_in * smoothing**2, per=int(closed), quiet=1
    )

    # Arc-length table: intervals of ~ds/4 of chord length, at least 8 per input point.
    num_intervals = max(8 * num_in, int(np.ceil(4.0 * u[-1] / ds)))
    edges, cum = _arc_length_table(tck, 0.0, u[-1], num_intervals)
    length = float(cum[-1])
    num_segments = int(round(length / ds))
    m = num_segments if closed else num_segments + 1
    if m < _MIN_GRID_POINTS:
        raise ValueError(
            f"from_centerline: ds={ds:g} m is too coarse for a {length:.3g} m track "
            f"(need at least {_MIN_GRID_POINTS} grid points)"
        )
    s_grid = np.arange(m) * (length / num_segments)

    # Invert s(u): linear interpolation in the table, refined by two Newton steps.
    uu = np.interp(s_grid, cum, edges)
    for _ in range(2):
        j = np.clip(np.searchsorted(edges, uu, side="right") - 1, 0, num_intervals - 1)
        s_uu = cum[j] + _arc_length_between(tck, edges[j], uu)
        dx, dy = interpolate.splev(uu, tck, der=1)
        uu = uu - (s_uu - s_grid) / np.hypot(dx, dy)

    px, py = interpolate.splev(uu, tck)
    dx, dy = interpolate.splev(uu, tck, der=1)
    ddx, ddy = interpolate.splev(uu, tck, der=2)
    kappa = (dx * ddy - dy * ddx) / np.hypot(dx, dy) ** 3
    heading = np.unwrap(np.arctan2(dy, dx))

    # Widths: each input point sits at spline parameter u_i, i.e. at arc length s(u_i).
    s_in = np.interp(u[:num_in], edges, cum)
    if closed:
        w_left = np.interp(s_grid, s_in, wl, period=length)
        w_right = np.interp(s_grid, s_in, wr, period=length)
    else:
        w_left = np.interp(s_grid, s_in, wl)
        w_right = np.interp(s_grid, s_in, wr)

    return Track(
        s=s_grid,
        kappa=kappa,
        width_left=w_left,
        width_right=w_right,
        x=np.asarray(px),
        y=np.asarray(py),
        heading=heading,
        length=length,
        closed=closed,
        name=name,
    )


def read_csv_rows(path: Path, columns: tuple[str, ...], extra_columns: bool = False) -> list[tuple[int, list[float]]]:
    """The numeric rows of a TUMFTM-style CSV file: ``(line number, [value per column])``
    for every line that is neither blank nor a ``#`` comment. Each row has exactly
    ``len(columns)`` comma-separated entries (at least that many with ``extra_columns``, the
    rest ignored), all finite numbers.

    Raises:
        ValueError: naming the file and line of a row with the wrong number of entries, a
            non-numeric or a non-finite one.
    """
    rows = []
    with Path(path).open("r", encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = [c.strip() for c in line.split(",")]
            if extra_columns and len(fields) < len(columns):
                raise ValueError(f"{path}:{lineno}: expected columns {','.join(columns)}, got {line!r}")
            if not extra_columns and len(fields) != len(columns):
                raise ValueError(f"{path}:{lineno}: expected {len(columns)} columns {','.join(columns)}, "
                                 f"got {len(fields)}: {line!r}")
            try:
                row = [float(c) for c in fields[:len(columns)]]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: non-numeric entry in {line!r}") from None
            if not all(np.isfinite(row)):
                raise ValueError(f"{path}:{lineno}: non-finite entry in {line!r}")
            rows.append((lineno, row))
    return rows


def from_csv(
    path: str | os.PathLike,
    ds: float = 1.0,
    smoothing: float = DEFAULT_SMOOTHING,
    name: str | None = None,
) -> Track:
    """Load a closed track in the TUMFTM racetrack-database CSV format.

    The file has a comment header ``# x_m,y_m,w_tr_right_m,w_tr_left_m`` and one row
    ``x,y,w_right,w_left`` [m] per centreline point (about 5 m apart); the loop is closed
    implicitly. Lines starting with ``#`` and blank lines are ignored. See
    :func:`from_centerline` for ``ds`` and ``smoothing``.

    Args:
        path: the CSV file.
        ds: requested grid spacing [m].
        smoothing: assumed positional noise sigma [m] of the centreline points.
        name: display name; defaults to the file stem.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: naming the file and line, for rows without exactly 4 columns,
            non-numeric or non-finite entries, non-positive widths, or fewer than 10 points.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"track file not found: {path}")
    rows = []
    for lineno, row in read_csv_rows(path, ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")):
        if row[2] <= 0 or row[3] <= 0:
            raise ValueError(
                f"{path}:{lineno}: track widths must be > 0 [m], got "
                f"w_tr_right_m={row[2]:g}, w_tr_left_m={row[3]:g}"
            )
        rows.append(row)
    if len(rows) < _MIN_CENTERLINE_POINTS:
        raise ValueError(
            f"{path}: need at least {_MIN_CENTERLINE_POINTS} centreline points, "
            f"got {len(rows)}"
        )
    data = np.asarray(rows, dtype=np.float64)
    try:
        return from_centerline(
            data[:, 0],
            data[:, 1],
            data[:, 2],
            data[:, 3],
            closed=True,
            ds=ds,
            smoothing=smoothing,
            name=path.stem if name is None else name,
        )
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def _polar_circuit(
    radius_fn: Callable[[np.ndarray], np.ndarray], width: float, ds: float, name: str
) -> Track:
    """Closed counter-clockwise track through the polar curve r(theta), noise-free."""
    if not (np.isfinite(width) and width > 0):
        raise ValueError(f"{name}: width must be > 0 [m], got {width!r}")
    theta = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)  # ~2 m apart at r = 200 m
    r = radius_fn(theta)
    half = np.full_like(theta, 0.5 * width)
    return from_centerline(
        r * np.cos(theta), r * np.sin(theta), half, half, closed=True, ds=ds, smoothing=0.0,
        name=name,
    )


def trefoil(
    radius: float = 200.0, lobe: float = 0.25, width: float = 12.0, ds: float = 1.0
) -> Track:
    """A closed, counter-clockwise three-lobed circuit ``r = radius (1 + lobe sin(3 theta))``.

    For ``lobe > 0.1`` the curve has three concave sections, i.e. right turns between the
    left-hand lobes (at ``sin(3 theta) = -1`` the curvature is
    ``(1 - 10 lobe) / (radius (1 - lobe)^2)``).

    Args:
        radius: mean radius [m].
        lobe: relative lobe amplitude, in ``[0, 1)``.
        width: total track width [m], split equally left/right.
        ds: requested grid spacing [m].
    """
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"trefoil: radius must be > 0 [m], got {radius!r}")
    if not 0.0 <= lobe < 1.0:
        raise ValueError(f"trefoil: lobe must be in [0, 1) so that r > 0, got {lobe!r}")
    return _polar_circuit(
        lambda th: radius * (1.0 + lobe * np.sin(3.0 * th)), width, ds, "trefoil"
    )


def random_circuit(
    seed: int,
    radius: float = 200.0,
    harmonics: int = 4,
    amplitude: float = 0.15,
    width: float = 12.0,
    ds: float = 1.0,
) -> Track:
    """A seeded random closed circuit: the star-shaped polar curve
    ``r = radius (1 + sum_k a_k sin(k theta + phi_k))``, ``k = 1..harmonics``, driven
    counter-clockwise.

    The amplitudes are random with ``sum_k |a_k| = amplitude < 0.5``, so
    ``r > 0.5 radius``; a star-shaped curve with ``r > 0`` never self-intersects. Higher
    harmonics get smaller amplitudes (``~ 1/k``) to keep the corners drivable. Note that
    large ``harmonics``/``amplitude`` can still produce corners tighter than the half-width.

    Args:
        seed: random seed; the same seed gives an identical track.
        radius: mean radius [m].
        harmonics: number of harmonics, >= 1.
        amplitude: total relative amplitude, in ``[0, 0.5)``.
        width: total track width [m], split equally left/right.
        ds: requested grid spacing [m].
    """
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"random_circuit: radius must be > 0 [m], got {radius!r}")
    if int(harmonics) < 1:
        raise ValueError(f"random_circuit: harmonics must be >= 1, got {harmonics!r}")
    if not 0.0 <= amplitude < 0.5:
        raise ValueError(
            f"random_circuit: amplitude must be in [0, 0.5) so that r > 0.5 radius, "
            f"got {amplitude!r}"
        )
    rng = np.random.default_rng(seed)
    k = np.arange(1, int(harmonics) + 1)
    a = rng.uniform(0.2, 1.0, k.shape) / k
    a *= amplitude / a.sum()
    phi = rng.uniform(0.0, 2.0 * np.pi, k.shape)

    def radius_fn(theta: np.ndarray) -> np.ndarray:
        return radius * (1.0 + np.sin(np.outer(theta, k) + phi) @ a)

    return _polar_circuit(radius_fn, width, ds, f"random_{seed}")


BUILTIN_TRACKS: dict[str, Callable[[], Track]] = {
    "straight": straight,
    "trefoil": trefoil,
    "random": lambda: random_circuit(0),
}


# --------------------------------------------------------------------------------------
# The shipped circuits: the TUMFTM racetrack-database (LGPL-3.0, see data/tracks/README.md).


def circuits_dir() -> Path:
    """The folder of the shipped circuits (``NAME.csv``), their racing lines
    (``racelines/NAME.csv``), their LGPL-3.0 ``LICENSE`` and ``README.md`` notice."""
    return Path(__file__).resolve().parent / "data" / "tracks"


@functools.lru_cache(maxsize=1)
def _circuit_files() -> dict[str, Path]:
    return {path.stem: path for path in sorted(circuits_dir().glob("*.csv"))}


def circuit_names() -> list[str]:
    """The names of the shipped real circuits (``"Austin"``, ..., ``"Zandvoort"``), sorted."""
    return list(_circuit_files())


def circuit_name(name: str) -> str | None:
    """The shipped circuit ``name`` refers to, in its own spelling (``"monza"`` -> ``"Monza"``;
    case is ignored), or ``None`` if it names none."""
    if not isinstance(name, str):
        return None
    lowered = {key.lower(): key for key in _circuit_files()}
    return lowered.get(name.lower())


@functools.lru_cache(maxsize=None)
def circuit(name: str, scale: float = 1.0) -> Track:
    """A shipped real circuit by name (any case), fitted by :func:`from_csv` with its defaults,
    at ``scale`` (:func:`scaled`; 0.1: a 1:10 model for the 1:10 car class).

    The fitted track is cached: the first load of a circuit fits its spline (about 0.1-0.3 s),
    later ones return the same immutable :class:`Track`.

    Raises:
        ValueError: for a name that is no shipped circuit, listing the known ones, or a scale
            that is not a finite number > 0.
    """
    canonical = circuit_name(name)
    if canonical is None:
        raise ValueError(f"unknown circuit {name!r}: the shipped circuits are {circuit_names()}")
    scale = check_scale(scale)
    if canonical != name or scale != 1.0:
        full = circuit(canonical)
        return full if scale == 1.0 else scaled(full, scale)
    return from_csv(_circuit_files()[canonical])


def raceline_path(name: str) -> Path:
    """The racing-line file (rows ``x_m, y_m``) of shipped circuit ``name`` (any case).

    Raises:
        ValueError: for a name that is no shipped circuit, listing the known ones.
    """
    canonical = circuit_name(name)
    if canonical is None:
        raise ValueError(f"no racing line is shipped for {name!r}: the shipped circuits are {circuit_names()}")
    return circuits_dir() / "racelines" / f"{canonical}.csv"


def track_names() -> list[str]:
    """Every name :func:`get_track` resolves: the built-in tracks, then the shipped circuits."""
    return list(BUILTIN_TRACKS) + circuit_names()


def get_track(name_or_path: str | os.PathLike | Track, scale: float = 1.0) -> Track:
    """Resolve a track: a :class:`Track` (returned as is), a builtin name (see
    ``BUILTIN_TRACKS``), a shipped circuit's name in any case (``"Monza"``, ``"spa"``, see
    :func:`circuit_names`; cached), or a path to a TUMFTM ``.csv`` file; at ``scale``
    (:func:`scaled`; 1, the default, as it is).

    Raises:
        ValueError: for a string that is none of these, listing the known names, or a scale
            that is not a finite number > 0.
        TypeError: for anything else (None, a number, ...), listing what a track may be.
    """
    scale = check_scale(scale)
    if scale != 1.0:
        if isinstance(name_or_path, str) and circuit_name(name_or_path) is not None:
            return circuit(name_or_path, scale)
        return scaled(get_track(name_or_path), scale)
    if isinstance(name_or_path, Track):
        return name_or_path
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise TypeError(f"track must be a Track, a builtin track name {sorted(BUILTIN_TRACKS)}, a shipped circuit's "
                        f"name (any case, e.g. 'Monza': `racing tracks` lists them) or the path of a TUMFTM .csv file; "
                        f"got {name_or_path!r}")
    key = os.fspath(name_or_path)
    if key in BUILTIN_TRACKS:
        return BUILTIN_TRACKS[key]()
    if circuit_name(key) is not None:
        return circuit(key)
    if key.lower().endswith(".csv") or Path(key).is_file():
        return from_csv(key)
    raise ValueError(
        f"unknown track {key!r}: expected a path to a .csv file, one of the builtin "
        f"tracks {sorted(BUILTIN_TRACKS)} or one of the shipped circuits {circuit_names()}"
    )


#: A corner for :func:`track_summary`: a stretch whose radius (curvature averaged over
#: CORNER_WINDOW) is below CORNER_RADIUS; stretches closer than CORNER_GAP are one corner.
CORNER_RADIUS = 100.0
CORNER_WINDOW = 10.0
CORNER_GAP = 30.0


def count_corners(track: Track) -> int:
    """Corners of a track: stretches where the centre line's radius, averaged over
    ``CORNER_WINDOW`` [m], is below ``CORNER_RADIUS`` [m]; stretches turning the same way less
    than ``CORNER_GAP`` [m] apart count once (a chicane, left then right, counts twice)."""
    kappa = np.asarray(track.kappa)
    m = kappa.shape[0]
    width = max(1, int(round(CORNER_WINDOW / track.ds)))
    kernel = np.ones(width) / width
    if track.closed:
        padded = np.concatenate([kappa[-width:], kappa, kappa[:width]])
        smooth = np.convolve(padded, kernel, mode="same")[width:width + m]
    else:
        smooth = np.convolve(kappa, kernel, mode="same")
    turning = np.where(np.abs(smooth) > 1.0 / CORNER_RADIUS, np.sign(smooth), 0.0)
    if not np.any(turning):
        return 0
    # Runs of equal non-zero direction, in grid order (rolled so a closed track starts on a straight).
    if track.closed:
        start = int(np.flatnonzero(turning == 0)[0]) if np.any(turning == 0) else 0
        turning = np.roll(turning, -start)
    runs: list[tuple[int, int, float]] = []  # (first, last, direction)
    k = 0
    while k < m:
        if turning[k] != 0:
            j = k
            while j + 1 < m and turning[j + 1] == turning[k]:
                j += 1
            runs.append((k, j, turning[k]))
            k = j + 1
        else:
            k += 1
    gap = CORNER_GAP / track.ds
    corners = 1
    for (_, last, d0), (first, _, d1) in zip(runs, runs[1:]):
        if d1 != d0 or first - last > gap:
            corners += 1
    if track.closed and len(runs) > 1:  # the last and the first run may be one corner
        (first, _, d0), (_, last, d1) = runs[0], runs[-1]
        if d0 == d1 and first + m - last <= gap:
            corners -= 1
    return corners


def track_summary(track: Track) -> dict[str, float | int | bool | str]:
    """Figures a racer reads: ``name``, ``length`` [m], ``closed``, ``mean_width`` and
    ``min_width`` [m] (left plus right), ``corners`` (:func:`count_corners`) and
    ``min_radius`` [m] (of the centre line; ``inf`` on a straight)."""
    width = np.asarray(track.width_left) + np.asarray(track.width_right)
    kappa_max = float(np.max(np.abs(track.kappa)))
    return {
        "name": track.name, "length": track.length, "closed": track.closed,
        "mean_width": float(width.mean()), "min_width": float(width.min()),
        "corners": count_corners(track), "min_radius": 1.0 / kappa_max if kappa_max > 0 else float("inf"),
    }
