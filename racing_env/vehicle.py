"""Vehicle parameters of the point-mass race car.

A :class:`VehicleParams` holds scalars for one car, or arrays of shape ``(N,)`` for a field
of ``N`` cars (see :func:`stack_vehicles`). It is a JAX pytree, so it can be passed into
jitted functions and vmapped over.

The speed-dependent limits, the drive limit ``ax_max(V)`` and the gg radius ``rho(V)``, come
from the paper's formula (``ax_max_0``, ``v_max``, ``rho_0``, ``rho_aero``) or from a
:class:`LimitTable` of their values at a few speeds. A table is interpolated linearly in
``V**2`` and extrapolated linearly beyond its ends, so the formula, which is linear in
``V**2``, is the two-point table ``[(0, ax_max_0, rho_0), (v_max, 0, rho(v_max))]`` exactly
(:meth:`VehicleParams.as_table`), and cars of different tables stack exactly onto the union
of their speeds (:func:`stack_vehicles`). The named classes built on these are in
:mod:`racing_env.car_classes`.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

ArrayLike = float | np.ndarray | jax.Array


def is_concrete(value: object) -> bool:
    """Whether ``value`` is a number or an array whose values are at hand (NumPy or JAX), as
    opposed to a tracer inside jit/vmap or a placeholder JAX unflattens a pytree with (such
    as vmap's axis specs)."""
    if isinstance(value, jax.core.Tracer):
        return False
    return isinstance(value, (int, float, np.ndarray, np.number, jax.Array))


def concrete_fields(params, names: Sequence[str] | None = None) -> dict[str, tuple[ArrayLike, np.ndarray]] | None:
    """A parameter dataclass's fields (``names``, default all) as ``{name: (value, float
    array)}``, each checked finite.

    ``None`` while any field is traced or abstract (inside jit/vmap): such values were
    validated when the concrete object was built. Concrete JAX arrays are checked like
    NumPy ones.
    """
    names = [f.name for f in dataclasses.fields(params)] if names is None else names
    values = {name: getattr(params, name) for name in names}
    if not all(map(is_concrete, values.values())):
        return None
    checked = {}
    for name, value in values.items():
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{type(params).__name__}.{name} must be finite, got {value!r}")
        checked[name] = (value, arr)
    return checked


def _interp_in_square(v: ArrayLike, speeds: ArrayLike, values: ArrayLike) -> jax.Array:
    """The piecewise-linear function of ``V**2`` through ``(speeds**2, values)`` at ``v``,
    extrapolated linearly from the first and last segments.

    ``speeds`` and ``values`` have shape ``(..., K)`` (one car ``(K,)``, stacked ``(N, K)``),
    ``v`` a shape that broadcasts against their leading shape (one car: any shape). JAX, and
    differentiable in ``v`` everywhere but at the knots (where the slope jumps).
    """
    v = jnp.asarray(v)
    speeds, values = jnp.asarray(speeds), jnp.asarray(values)
    w = (v * v)[..., None]
    knots = speeds * speeds
    segment = jnp.sum(w >= knots[..., 1:-1], axis=-1)  # 0 .. K-2; the end segments extrapolate
    slopes = jnp.diff(values, axis=-1) / jnp.diff(knots, axis=-1)
    lines = values[..., :-1] + slopes * (w - knots[..., :-1])  # (..., K-1): each segment's line at v
    return jnp.take_along_axis(lines, segment[..., None], axis=-1)[..., 0]


def interp_in_square_np(v: np.ndarray, speeds: np.ndarray, values: np.ndarray) -> np.ndarray:
    """:func:`_interp_in_square` of one car's table in NumPy, exact at the table's own speeds
    (which :func:`stack_vehicles` relies on: a car's knots keep their values bit for bit)."""
    v = np.asarray(v, dtype=np.float64)
    w, knots = v * v, speeds * speeds
    segment = np.clip(np.searchsorted(knots, w, side="right") - 1, 0, len(knots) - 2)
    slope = (values[segment + 1] - values[segment]) / (knots[segment + 1] - knots[segment])
    out = values[segment] + slope * (w - knots[segment])
    exact = np.searchsorted(speeds, v)
    hit = (exact < len(speeds)) & (speeds[np.minimum(exact, len(speeds) - 1)] == v)
    return np.where(hit, values[np.minimum(exact, len(speeds) - 1)], out)


@dataclasses.dataclass(frozen=True, eq=False)
class LimitTable:
    """A car's speed-dependent limits at ``K >= 2`` speeds (stacked: ``(N, K)`` per field).

    Between the speeds a limit is linear in ``V**2`` (the paper's formula is, so a two-point
    table reproduces it), and beyond the first and last speeds it continues the end
    segments' lines. The drive limit must be positive up to the car's top speed, where it is
    zero (so a car driven flat out approaches the top speed, as with the formula), and not
    positive beyond it.

    Attributes:
        speeds: ``(K,)`` speeds [m/s] from 0, strictly increasing.
        ax_max: ``(K,)`` largest positive longitudinal acceleration (drive) [m/s^2].
        rho: ``(K,)`` radius of the gg diagram [m/s^2], ``> 0``.
    """

    speeds: ArrayLike
    ax_max: ArrayLike
    rho: ArrayLike

    def __post_init__(self) -> None:
        fields = concrete_fields(self)
        if fields is None:
            return
        speeds, ax, rho = (fields[name][1] for name in ("speeds", "ax_max", "rho"))
        if not (speeds.shape == ax.shape == rho.shape) or speeds.ndim < 1 or speeds.shape[-1] < 2:
            raise ValueError("LimitTable: speeds, ax_max and rho must be arrays of one shape (K,) (stacked "
                             f"(N, K)) with K >= 2 speeds, got shapes {speeds.shape}, {ax.shape}, {rho.shape}")
        for row_speeds, row_ax, row_rho in zip(*(a.reshape(-1, a.shape[-1]) for a in (speeds, ax, rho))):
            if row_speeds[0] != 0 or np.any(np.diff(row_speeds) <= 0):
                raise ValueError("LimitTable.speeds must start at 0 m/s and be strictly increasing, got "
                                 f"{row_speeds.tolist()}")
            if np.any(row_rho <= 0):
                raise ValueError(f"LimitTable.rho (the gg radius) must be > 0 m/s^2 at every speed, got {row_rho.tolist()}")
            top = np.flatnonzero(row_ax <= 0)
            if top.size == 0 or top[0] == 0 or row_ax[top[0]] != 0 or np.any(row_ax[top[0]:] > 0):
                raise ValueError("LimitTable.ax_max (the drive limit) must be > 0 m/s^2 up to the top speed, exactly "
                                 f"0 there and not positive beyond it, got {row_ax.tolist()} at speeds {row_speeds.tolist()}")

    def __eq__(self, other: object) -> bool:
        """Equal tables: the same values at the same speeds (concrete tables)."""
        if not isinstance(other, LimitTable):
            return NotImplemented
        return all(np.array_equal(np.asarray(getattr(self, name)), np.asarray(getattr(other, name)))
                   for name in ("speeds", "ax_max", "rho"))

    def __hash__(self) -> int:
        """From the values (concrete tables), so that a car with a table can key a cache."""
        return hash(tuple(np.asarray(getattr(self, name), dtype=float).tobytes() for name in ("speeds", "ax_max", "rho")))

    @property
    def top_speed(self) -> np.ndarray:
        """The speed [m/s] where the drive limit is zero, ``()`` (stacked ``(N,)``); concrete
        tables only."""
        speeds, ax = np.asarray(self.speeds, dtype=float), np.asarray(self.ax_max, dtype=float)
        return np.take_along_axis(speeds, np.argmax(ax <= 0, axis=-1)[..., None], axis=-1)[..., 0]

    def row(self, index: int) -> "LimitTable":
        """The table of car ``index`` of a stacked ``(N, K)`` table."""
        return LimitTable(*(np.asarray(getattr(self, name), dtype=float)[index] for name in ("speeds", "ax_max", "rho")))

    def resample(self, speeds: np.ndarray) -> "LimitTable":
        """This (one car's) table at other ``speeds (K',)``: the same function where ``speeds``
        include this table's own (exact at them, linear in ``V**2`` between)."""
        own = [np.asarray(getattr(self, name), dtype=float) for name in ("speeds", "ax_max", "rho")]
        speeds = np.asarray(speeds, dtype=float)
        return LimitTable(speeds, interp_in_square_np(speeds, own[0], own[1]), interp_in_square_np(speeds, own[0], own[2]))


jax.tree_util.register_dataclass(LimitTable, data_fields=["speeds", "ax_max", "rho"], meta_fields=[])

#: The fields of :class:`VehicleParams` that are numbers (one per car); ``table`` is not one.
SCALAR_FIELDS = ("length", "width", "v_max", "ax_max_0", "rho_0", "rho_aero", "jx_max", "jy_max",
                 "min_turn_radius", "mass", "c_drag")
#: The fields that may be zero (the others must be > 0).
_NON_NEGATIVE_FIELDS = ("rho_aero", "c_drag")


@dataclasses.dataclass(frozen=True)
class VehicleParams:
    """Physical limits of one car (or, stacked, of N cars).

    Attributes:
        length: footprint length l_veh [m].
        width: footprint width w_veh [m].
        v_max: top speed [m/s] in still air. Enforced through ``ax_max(V)``, which falls to
            zero at v_max (and becomes negative above it, so a car faster than v_max
            decelerates); a car with drag in another car's slipstream can exceed it.
        ax_max_0: largest positive longitudinal acceleration at standstill [m/s^2].
        rho_0: radius of the gg diagram (combined acceleration limit) at standstill [m/s^2].
        rho_aero: growth of the gg radius with speed squared (downforce) [1/m],
            ``rho(V) = rho_0 + rho_aero * V**2``.
        jx_max: longitudinal jerk limit [m/s^3]; scales the env's normalised actions.
        jy_max: lateral jerk limit [m/s^3].
        min_turn_radius: tightest turning radius the steering allows [m], which caps the
            lateral acceleration at ``V**2 / min_turn_radius`` (see ``ay_turn_max``). Not in
            the paper: its point mass turns on the spot.
        mass: [kg] what the car weighs in a contact (:mod:`racing_env.contact`): only the
            ratio of two cars' masses matters. Not in the paper, whose cars never touch.
        c_drag: aerodynamic drag per unit mass ``rho_air Cd A / (2 m)`` [1/m]: the drag
            decelerates the car by ``c_drag V^2`` (:mod:`racing_env.dynamics`), less in another
            car's slipstream. 0 (the default, the paper's car): no drag, and ``ax`` is the
            car's acceleration. With drag, ``ax`` is the acceleration the tyres deliver and
            ``ax_max(V)`` stays the net limit in still air, the drive minus the drag, so the
            drive limit on ``ax`` is ``drive_max(V) = ax_max(V) + c_drag V^2`` (docs/model.md).
        table: ``None`` (the paper's formula for ``ax_max(V)`` and ``rho(V)``), or a
            :class:`LimitTable` that gives them instead. With a table, ``v_max`` is the
            table's top speed and ``ax_max_0``, ``rho_0`` and ``rho_aero`` describe the table
            at standstill (its values at ``V = 0`` and the gg radius's slope in ``V**2`` on
            its first segment); build such a car with :meth:`from_table`.
    """

    length: ArrayLike = 4.7
    width: ArrayLike = 2.0
    v_max: ArrayLike = 25.0
    ax_max_0: ArrayLike = 8.0
    rho_0: ArrayLike = 12.0
    rho_aero: ArrayLike = 0.004
    jx_max: ArrayLike = 30.0
    jy_max: ArrayLike = 30.0
    # A road car's turning circle is about 11 m across. The cap binds below ~8 m/s only,
    # so racing-speed results (and the paper's scenario) do not feel it.
    min_turn_radius: ArrayLike = 5.0
    mass: ArrayLike = 800.0
    table: LimitTable | None = None
    c_drag: ArrayLike = 0.0

    def __post_init__(self) -> None:
        checked = concrete_fields(self, SCALAR_FIELDS)
        for name, (value, arr) in (checked or {}).items():
            lower_ok = arr >= 0 if name in _NON_NEGATIVE_FIELDS else arr > 0
            if not np.all(lower_ok):
                allowed = ">= 0" if name in _NON_NEGATIVE_FIELDS else "> 0"
                raise ValueError(f"VehicleParams.{name} must be {allowed}, got {value!r}")
        if self.table is None or checked is None or concrete_fields(self.table) is None:
            return
        if not isinstance(self.table, LimitTable):
            raise ValueError(f"VehicleParams.table must be a LimitTable or None, got {type(self.table).__name__}")
        implied = _table_formula_fields(self.table)
        for name, value in implied.items():
            given = np.asarray(getattr(self, name), dtype=float)
            if not np.allclose(given, value, rtol=1e-9, atol=1e-12):
                raise ValueError(
                    f"VehicleParams.{name} = {getattr(self, name)!r} disagrees with its limit table, which gives "
                    f"{np.asarray(value).tolist()}: a car with a table takes v_max, ax_max_0, rho_0 and rho_aero from it "
                    "(build it with VehicleParams.from_table, or change the table)")

    @classmethod
    def from_table(cls, table: LimitTable, **fields: ArrayLike) -> "VehicleParams":
        """A car whose ``ax_max(V)`` and ``rho(V)`` are ``table``'s; ``v_max``, ``ax_max_0``,
        ``rho_0`` and ``rho_aero`` are set from the table, the other fields from ``fields``.

        Raises:
            ValueError: for a bad table (see :class:`LimitTable`) or a formula field in ``fields``.
        """
        clash = sorted(set(fields) & {"v_max", "ax_max_0", "rho_0", "rho_aero", "table"})
        if clash:
            raise ValueError(f"VehicleParams.from_table: {clash} come from the table; give only "
                             f"{[f for f in SCALAR_FIELDS if f not in ('v_max', 'ax_max_0', 'rho_0', 'rho_aero')]}")
        if not isinstance(table, LimitTable):
            raise ValueError(f"VehicleParams.from_table needs a LimitTable, got {type(table).__name__}")
        return cls(**fields, **{k: float(v) if np.ndim(v) == 0 else v
                                for k, v in _table_formula_fields(table).items()}, table=table)

    def as_table(self) -> "VehicleParams":
        """This car with its limits as a table: itself if it has one, else the formula's exact
        two-point table ``[(0, ax_max_0, rho_0), (v_max, 0, rho(v_max))]`` (one car only)."""
        if self.table is not None:
            return self
        v_max = float(self.v_max)
        table = LimitTable(np.array([0.0, v_max]), np.array([float(self.ax_max_0), 0.0]),
                           np.array([float(self.rho_0), float(self.rho_0) + float(self.rho_aero) * v_max**2]))
        return dataclasses.replace(self, table=table)

    def ax_max(self, v: jax.Array) -> jax.Array:
        """Largest positive longitudinal acceleration at speed ``v`` [m/s^2].

        Formula: ``ax_max_0 * (1 - (v / v_max)**2)``: zero at v_max and negative beyond it.
        Table: the table's drive limit (linear in ``v**2`` between its speeds), likewise zero
        at v_max and negative beyond it.
        """
        if self.table is not None:
            return _interp_in_square(v, self.table.speeds, self.table.ax_max)
        return self.ax_max_0 * (1.0 - (v / self.v_max) ** 2)

    def drag(self, v: jax.Array) -> jax.Array:
        """Deceleration by aerodynamic drag in still air at speed ``v`` [m/s^2]:
        ``c_drag v |v|`` (against the motion; zero for a car without drag)."""
        return self.c_drag * v * jnp.abs(v)

    def drive_max(self, v: jax.Array) -> jax.Array:
        """Largest positive value of the acceleration state ``ax`` at speed ``v`` [m/s^2]: the
        net limit ``ax_max(v)`` plus the still-air drag ``c_drag v^2`` the drive overcomes
        there. For a car without drag ``ax_max(v)`` itself (the same values)."""
        return self.ax_max(v) + self.c_drag * v * v

    def rho(self, v: jax.Array) -> jax.Array:
        """Radius of the gg diagram at speed ``v`` [m/s^2] (formula or table)."""
        if self.table is not None:
            return _interp_in_square(v, self.table.speeds, self.table.rho)
        return self.rho_0 + self.rho_aero * v**2

    def ay_turn_max(self, v: jax.Array) -> jax.Array:
        """Largest lateral acceleration the steering allows at speed ``v`` [m/s^2].

        ``v**2 / min_turn_radius``: a car at walking pace cannot turn faster than
        ``v / min_turn_radius`` [rad/s], while the point mass's heading rate ``ay / V`` would
        grow without bound as ``V -> 0`` (the planners used it to spin cars on the spot).
        """
        return v**2 / self.min_turn_radius

    @property
    def jerk_max(self) -> jax.Array:
        """Jerk limits ``[jx_max, jy_max]``, shape ``(..., 2)`` [m/s^3]."""
        return jnp.stack([jnp.asarray(self.jx_max), jnp.asarray(self.jy_max)], axis=-1)

    def car(self, index: int) -> "VehicleParams":
        """The scalar parameters of car ``index`` from stacked ``(N,)`` fields."""
        return VehicleParams(
            **{name: float(np.asarray(getattr(self, name))[index]) for name in SCALAR_FIELDS},
            table=None if self.table is None else self.table.row(index),
        )

    def cars(self, num_cars: int) -> list["VehicleParams"]:
        """The ``num_cars`` cars of stacked ``(N,)`` fields, or this one car ``num_cars`` times."""
        if np.ndim(self.v_max) == 0:
            return [self] * num_cars
        return [self.car(i) for i in range(num_cars)]

    def key(self) -> tuple:
        """A hashable description of one car (for caches): its numbers and its table."""
        numbers = tuple(float(getattr(self, name)) for name in SCALAR_FIELDS)
        if self.table is None:
            return numbers, None
        return numbers, tuple(tuple(np.asarray(getattr(self.table, name), dtype=float).tolist())
                              for name in ("speeds", "ax_max", "rho"))

    @classmethod
    def from_key(cls, key: tuple) -> "VehicleParams":
        """The car of :meth:`key`."""
        numbers, table = key
        return cls(**dict(zip(SCALAR_FIELDS, numbers)),
                   table=None if table is None else LimitTable(*(np.asarray(t) for t in table)))

    def replace(self, **changes: ArrayLike) -> "VehicleParams":
        return dataclasses.replace(self, **changes)


def _table_formula_fields(table: LimitTable) -> dict[str, np.ndarray]:
    """``v_max``, ``ax_max_0``, ``rho_0`` and ``rho_aero`` of a concrete table: its top speed,
    its values at standstill and the gg radius's slope in ``V**2`` on its first segment."""
    speeds, ax, rho = (np.asarray(getattr(table, name), dtype=float) for name in ("speeds", "ax_max", "rho"))
    rows = speeds.reshape(-1, speeds.shape[-1]), ax.reshape(-1, ax.shape[-1]), rho.reshape(-1, rho.shape[-1])
    zero = np.zeros(1)
    ax0 = np.array([interp_in_square_np(zero, s, a)[0] for s, a in zip(rows[0], rows[1])])
    rho0 = np.array([interp_in_square_np(zero, s, r)[0] for s, r in zip(rows[0], rows[2])])
    slope = (rows[2][:, 1] - rows[2][:, 0]) / (rows[0][:, 1] ** 2 - rows[0][:, 0] ** 2)
    shape = speeds.shape[:-1]
    return {"v_max": np.asarray(table.top_speed, dtype=float).reshape(shape), "ax_max_0": ax0.reshape(shape),
            "rho_0": rho0.reshape(shape), "rho_aero": np.maximum(slope, 0.0).reshape(shape)}


jax.tree_util.register_dataclass(
    VehicleParams,
    data_fields=[f.name for f in dataclasses.fields(VehicleParams)],
    meta_fields=[],
)


def stack_vehicles(vehicles: Sequence[VehicleParams]) -> VehicleParams:
    """Stack per-car parameters into one ``VehicleParams`` whose fields have shape ``(N,)``.

    If any car has a :class:`LimitTable`, every car's limits become a table on the union of
    the cars' speeds (a formula car its exact two-point table, :meth:`VehicleParams.as_table`),
    so the stacked table ``(N, K)`` gives each car the limits it had alone.
    """
    if len(vehicles) < 1:
        raise ValueError("stack_vehicles needs at least one VehicleParams")
    numbers = {name: np.array([float(getattr(v, name)) for v in vehicles]) for name in SCALAR_FIELDS}
    if all(v.table is None for v in vehicles):
        return VehicleParams(**numbers)
    tables = [v.as_table().table for v in vehicles]
    for i, table in enumerate(tables):
        if np.ndim(table.speeds) != 1:
            raise ValueError(f"stack_vehicles: car {i} is already stacked (its table has shape {np.shape(table.speeds)})")
    speeds = np.unique(np.concatenate([np.asarray(t.speeds, dtype=float) for t in tables]))
    common = [t.resample(speeds) for t in tables]
    table = LimitTable(*(np.stack([np.asarray(getattr(t, name)) for t in common])
                         for name in ("speeds", "ax_max", "rho")))
    # the formula fields from the stacked table (a formula car's rho_aero is its first segment's, unchanged
    # where its curve is one line in V**2, as the formula's is)
    return VehicleParams(**{**numbers, **_table_formula_fields(table)}, table=table)
