"""Vehicle parameters of the point-mass race car.

A :class:`VehicleParams` holds scalars for one car, or arrays of shape ``(N,)`` for a field
of ``N`` cars (see :func:`stack_vehicles`). It is a JAX pytree, so it can be passed into
jitted functions and vmapped over.
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


def concrete_fields(params) -> dict[str, tuple[ArrayLike, np.ndarray]] | None:
    """A parameter dataclass's fields as ``{name: (value, float array)}``, each checked finite.

    ``None`` while any field is traced or abstract (inside jit/vmap): such values were
    validated when the concrete object was built. Concrete JAX arrays are checked like
    NumPy ones.
    """
    values = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    if not all(map(is_concrete, values.values())):
        return None
    checked = {}
    for name, value in values.items():
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{type(params).__name__}.{name} must be finite, got {value!r}")
        checked[name] = (value, arr)
    return checked


@dataclasses.dataclass(frozen=True)
class VehicleParams:
    """Physical limits of one car (or, stacked, of N cars).

    Attributes:
        length: footprint length l_veh [m].
        width: footprint width w_veh [m].
        v_max: top speed [m/s]. Enforced through ``ax_max(V)``, which falls to zero at v_max
            (and becomes negative above it, so a car faster than v_max decelerates).
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

    def __post_init__(self) -> None:
        for name, (value, arr) in (concrete_fields(self) or {}).items():
            lower_ok = arr >= 0 if name == "rho_aero" else arr > 0
            if not np.all(lower_ok):
                allowed = ">= 0" if name == "rho_aero" else "> 0"
                raise ValueError(f"VehicleParams.{name} must be {allowed}, got {value!r}")

    def ax_max(self, v: jax.Array) -> jax.Array:
        """Largest positive longitudinal acceleration at speed ``v`` [m/s^2].

        ``ax_max_0 * (1 - (v / v_max)**2)``: zero at v_max and negative beyond it.
        """
        return self.ax_max_0 * (1.0 - (v / self.v_max) ** 2)

    def rho(self, v: jax.Array) -> jax.Array:
        """Radius of the gg diagram at speed ``v`` [m/s^2]."""
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
            **{f.name: float(np.asarray(getattr(self, f.name))[index]) for f in dataclasses.fields(self)}
        )

    def replace(self, **changes: ArrayLike) -> "VehicleParams":
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    VehicleParams,
    data_fields=[f.name for f in dataclasses.fields(VehicleParams)],
    meta_fields=[],
)


def stack_vehicles(vehicles: Sequence[VehicleParams]) -> VehicleParams:
    """Stack per-car parameters into one ``VehicleParams`` whose fields have shape ``(N,)``."""
    if len(vehicles) < 1:
        raise ValueError("stack_vehicles needs at least one VehicleParams")
    fields = [f.name for f in dataclasses.fields(VehicleParams)]
    return VehicleParams(
        **{name: np.array([float(getattr(v, name)) for v in vehicles]) for name in fields}
    )
