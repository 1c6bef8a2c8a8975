"""The agents' observation vectors (pure JAX, all cars at once).

Observation of car i, shape ``(8 + 7 K + 3 P,)`` with P preview distances and K rival
blocks (``K = N - 1`` by default, or the ``observed_rivals`` of the race):

* own state: ``V, n, chi, ax, ay``, room to the left boundary ``w_left(s) - n``, room to the
  right boundary ``w_right(s) + n``, and the fraction of the race still to go;
* a block per rival: wrapped gap ``ds``, ``dn``, ``dV``, ``dchi``, its ``ax``, ``ay`` and
  whether it is still racing (1/0). By default every other car j, in cyclic order
  ``i+1, ..., i-1``. With ``observed_rivals = K`` the K cars nearest by wrapped ``|ds|``
  (ahead or behind alike; equal distances to the lower index), nearest first, whatever N:
  a policy trained in a duel then reads a field the same way. Blocks beyond the N - 1
  rivals of a small field are zeros with the racing flag 0 (an absent car);
* the track ahead at each preview distance d: ``kappa(s+d)``, ``w_left(s+d)``, ``w_right(s+d)``.

Units (``RaceConfig.observation_units``, :data:`OBSERVATION_UNITS`): ``scaled`` (the default)
divides each feature by a scale of the observing car and the track, so that a network at its
default initialisation reads numbers of order one; ``physical`` gives them in m, m/s, rad,
m/s^2 and 1/m. The scales (:func:`observation_scale`), for a car of top speed ``v_max`` and
gg radius at top speed ``a_ref = rho(v_max)`` on a track of mean half-width ``w_ref``:

* speeds ``V`` and ``dV`` over ``v_max``;
* accelerations over ``a_ref``;
* lateral offsets ``n``, ``dn``, the rooms to the boundaries and the previewed widths over
  ``w_ref``;
* the gap ``ds`` over ``v_max *`` :data:`GAP_SECONDS` (the distance the car covers in that
  time at top speed);
* curvature times ``v_max^2 / a_ref``, the radius of the tightest corner the car takes at top
  speed: 1 where a corner's limit speed is ``v_max``, 4 where it is half of it;
* headings [rad], the fraction to go and the racing flags as they are.

Scaling is a product by fixed weights (the same for every step of a race), so the two units
convert exactly: ``scaled = physical * observation_scale(...)``. The weights are the race's
``RaceParams.obs_scale``. In physical units the curvature that announces a bend is a
thousandth of the speed's scale at a network's input, and stable-baselines3's PPO at its
defaults does not learn to lap on them (docs/rl.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import AX, AY, CHI, N_LAT, S, V
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

OWN_FEATURES = 8
OTHER_FEATURES = 7
PREVIEW_FEATURES = 3
OBSERVATION_UNITS = ("scaled", "physical")
"""What an observation's numbers are in (``RaceConfig.observation_units``): ``scaled`` (the
default, every feature over a scale of the car and track) or ``physical`` (SI units)."""
GAP_SECONDS = 4.0
"""[s] The rival gap ``ds`` is scaled by the distance the observing car covers in this time at
its top speed (100 m for the paper's car)."""


def check_observation_units(units: str) -> None:
    """Refuse an unknown ``observation_units``, naming the allowed ones."""
    if units not in OBSERVATION_UNITS:
        raise ValueError(f"observation_units must be one of {OBSERVATION_UNITS}, got {units!r}")


def observation_scale(track: Track, vehicles: VehicleParams, num_preview: int, observed_rivals: int | None = None,
                      units: str = "scaled") -> np.ndarray:
    """The weights each car's observation is multiplied by, ``(N, O)`` float64 (module
    docstring): all ones for ``physical``.

    Args:
        track: the race's track (its mean half-width is the lateral scale).
        vehicles: the cars' parameters, fields ``(N,)``: their top speeds ``v_max`` [m/s] and
            gg radius at top speed ``a_ref = rho(v_max)`` [m/s^2] set the scales.
        num_preview: number of preview distances P.
        observed_rivals: the race's nearest-rival blocks K, or None (every other car).
        units: one of :data:`OBSERVATION_UNITS`.
    """
    check_observation_units(units)
    v_max = np.atleast_1d(np.asarray(vehicles.v_max, np.float64))
    a_ref = np.atleast_1d(np.asarray(vehicles.rho(v_max), np.float64))
    num_cars = v_max.shape[0]
    size = observation_size(num_cars, num_preview, observed_rivals)
    if units == "physical":
        return np.ones((num_cars, size))
    w_ref = float(np.mean(np.asarray(track.width_left) + np.asarray(track.width_right))) / 2.0
    one = np.ones(num_cars)
    own = [1 / v_max, one / w_ref, one, 1 / a_ref, 1 / a_ref, one / w_ref, one / w_ref, one]
    rival = [1 / (v_max * GAP_SECONDS), one / w_ref, 1 / v_max, one, 1 / a_ref, 1 / a_ref, one]
    ahead = [v_max**2 / a_ref, one / w_ref, one / w_ref]
    rivals = num_cars - 1 if observed_rivals is None else observed_rivals
    columns = own + rival * rivals + ahead * num_preview
    return np.stack(columns, axis=-1)


def observation_size(num_cars: int, num_preview: int, observed_rivals: int | None = None) -> int:
    """The length of an observation: ``N - 1`` rival blocks, or ``observed_rivals``."""
    rivals = num_cars - 1 if observed_rivals is None else observed_rivals
    return OWN_FEATURES + OTHER_FEATURES * rivals + PREVIEW_FEATURES * num_preview


def cars_racing(observation: np.ndarray | None, index: int, num_cars: int,
                observed_rivals: int | None = None) -> np.ndarray:
    """Which cars are still racing, ``(num_cars,)`` bool, as car ``index``'s observation says
    (its own entry True). The env's flags describe the cars after the step just taken
    (a car that finished or retired in it is already out). All True when ``observation``
    is None or not of this layout's size, and with ``observed_rivals`` (the race's; its
    blocks do not say which car they describe). A transformed observation of the same size
    (e.g. normalised by a wrapper) cannot be told apart and is read as if raw: planners must
    be given the env's own observations."""
    racing = np.ones(num_cars, dtype=bool)
    if observation is None or observed_rivals is not None:
        return racing
    obs = np.asarray(observation)
    rest = obs.size - observation_size(num_cars, 0)
    if obs.ndim != 1 or rest < 0 or rest % PREVIEW_FEATURES:
        return racing
    flags = obs[OWN_FEATURES + OTHER_FEATURES - 1 : OWN_FEATURES + OTHER_FEATURES * (num_cars - 1) : OTHER_FEATURES]
    racing[(index + 1 + np.arange(num_cars - 1)) % num_cars] = flags > 0.5
    return racing


def observe(
    x: jax.Array,
    active: jax.Array,
    track: Track,
    finish_s: jax.Array,
    preview: jax.Array,
    observed_rivals: int | None = None,
    scale: jax.Array | None = None,
) -> jax.Array:
    """Observations of all cars: ``x (N, 6)``, ``active (N,)`` -> ``(N, obs_size)``;
    ``observed_rivals`` (static): the K nearest rivals' blocks instead of every other car's;
    ``scale (N, obs_size)``: each car's row multiplies its observation
    (:func:`observation_scale`), None: physical units."""
    num_cars = x.shape[0]
    s, n = x[:, S], x[:, N_LAT]
    to_go = jnp.clip((finish_s - s) / finish_s, 0.0, 1.0)
    own = jnp.stack(
        [
            x[:, V],
            n,
            x[:, CHI],
            x[:, AX],
            x[:, AY],
            track.width_left_at(s) - n,
            track.width_right_at(s) + n,
            to_go,
        ],
        axis=-1,
    )
    # others[i, k] describes car (i + k) % N for k = 1..N-1
    idx = (jnp.arange(num_cars)[:, None] + jnp.arange(1, num_cars)[None, :]) % num_cars
    if observed_rivals is not None:  # the cars of idx by |ds|, nearest first (stable: lower index on ties)
        cyclic_gap = jnp.abs(track.wrap_ds(x[idx, S] - s[:, None]))
        by_index = jnp.argsort(idx, axis=1)  # the blocks in index order, so that ties go to the lower index
        idx = jnp.take_along_axis(idx, by_index, axis=1)
        nearest = jnp.argsort(jnp.take_along_axis(cyclic_gap, by_index, axis=1), axis=1, stable=True)
        idx = jnp.take_along_axis(idx, nearest, axis=1)[:, :observed_rivals]
    xo = x[idx]  # (N, K, 6)
    others = jnp.stack(
        [
            track.wrap_ds(xo[..., S] - s[:, None]),
            xo[..., N_LAT] - n[:, None],
            xo[..., V] - x[:, None, V],
            xo[..., CHI] - x[:, None, CHI],
            xo[..., AX],
            xo[..., AY],
            active[idx].astype(x.dtype),
        ],
        axis=-1,
    )
    if observed_rivals is not None and observed_rivals > num_cars - 1:  # absent cars: zeros, not racing
        others = jnp.pad(others, ((0, 0), (0, observed_rivals - (num_cars - 1)), (0, 0)))
    others = others.reshape(num_cars, -1)
    s_ahead = s[:, None] + preview[None, :]
    ahead = jnp.stack(
        [track.kappa_at(s_ahead), track.width_left_at(s_ahead), track.width_right_at(s_ahead)],
        axis=-1,
    ).reshape(num_cars, -1)
    physical = jnp.concatenate([own, others, ahead], axis=-1)
    return physical if scale is None else physical * scale
