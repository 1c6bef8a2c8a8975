"""Cars of real racing classes by name: :class:`VehicleParams` presets with their sources.

Each class is built from published figures (listed with each class below and in
docs/model.md, "Car classes"); what no source gives is said so. The limits of the table
classes are :class:`racing_env.vehicle.LimitTable` s: the source's values at the source's
speeds. A class whose source gives its drag (``tum``, ``av21``) has it (``c_drag``, the drag
per unit mass): its table's drive limit ``ax_max`` is then the net limit in still air, the
source's drive less the drag (:func:`net_of_drag`), which falls to zero at the top speed where
they are equal; a car in another's slipstream has less drag and more to spare
(:mod:`racing_env.dynamics`). A class without drag (``f1tenth``, whose source has none) has
its top speed enforced as the paper's formula enforces it: the drive limit falls to zero at
the top speed, here linearly in ``V**2`` from the last source speed below it.

* ``paper``: the paper's car (M. Rowold, arXiv:2310.00766), the default of every command.
* ``tum``: TUM's research car of TUMFTM/global_racetrajectory_optimization.
* ``av21``: the Dallara AV-21 of the Indy Autonomous Challenge.
* ``f1tenth``: the 1:10-scale car of f1tenth/f1tenth_gym.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from racing_env.vehicle import LimitTable, VehicleParams, interp_in_square_np

#: Where no source gives jerk limits, a full-size class reaches its largest gg radius in the time
#: the paper's car reaches its 12 m/s^2 at 30 m/s^3 [s] (so the AV-21, 32 m/s^2 at its top
#: speed, gets 81 m/s^3; TUM's car, 12 m/s^2, the paper's 30 m/s^3).
JERK_RISE_TIME = 12.0 / 30.0
#: Standard gravity [m/s^2] (the value TUMFTM's racecar.ini uses).
GRAVITY = 9.81
#: Air density [kg/m^3] at sea level and 15 degrees C.
AIR_DENSITY = 1.225


@dataclasses.dataclass(frozen=True)
class CarClass:
    """A named class: its car and where its figures come from.

    Attributes:
        name: what ``--car`` takes.
        title: a few words that say what car it is.
        source: the sources of its figures (repository and file, or document).
        build: makes the :class:`VehicleParams`.
        source_speeds: the speeds [m/s] at which the source gives the limits (empty for the
            formula class).
        source_ax_max: the source's drive limit [m/s^2] at ``source_speeds``.
        source_rho: the source's gg radius [m/s^2] at ``source_speeds``.
    """

    name: str
    title: str
    source: str
    build: Callable[[], VehicleParams]
    source_speeds: tuple[float, ...] = ()
    source_ax_max: tuple[float, ...] = ()
    source_rho: tuple[float, ...] = ()

    def vehicle(self) -> VehicleParams:
        return self.build()


def table_with_top_speed(speeds, ax_max, rho, top_speed: float) -> LimitTable:
    """A :class:`LimitTable` of a source's ``speeds (K,)`` [m/s], drive limits ``ax_max (K,)``
    and gg radii ``rho (K,)`` [m/s^2], kept at the speeds below ``top_speed`` [m/s]; the drive
    limit then falls to zero at ``top_speed``, where the gg radius is the source's
    (interpolated linearly in ``V**2``, or continued from its last two speeds)."""
    speeds, ax_max, rho = (np.asarray(a, dtype=float) for a in (speeds, ax_max, rho))
    keep = speeds < top_speed
    if not np.any(keep):
        raise ValueError(f"table_with_top_speed: no source speed below the top speed {top_speed} m/s")
    rho_top = interp_in_square_np(np.array([top_speed]), speeds, rho)[0]
    return LimitTable(np.append(speeds[keep], top_speed), np.append(ax_max[keep], 0.0), np.append(rho[keep], rho_top))


def net_of_drag(speeds, drive, rho, c_drag: float, top_speed: float) -> LimitTable:
    """The still-air :class:`LimitTable` of a car with drag: at the source's ``speeds (K,)``
    [m/s] the net drive ``drive - c_drag V^2`` [m/s^2] (``drive (K,)`` the source's drive limit,
    ``c_drag`` [1/m] the drag per unit mass) and the gg radius ``rho (K,)``, up to the top
    speed: the speed where the net drive reaches zero between two source speeds (exactly
    where the drive and the drag are equal on that segment: both are linear in ``V**2``
    there), or else ``top_speed`` [m/s] (:func:`table_with_top_speed`)."""
    speeds, drive, rho = (np.asarray(a, dtype=float) for a in (speeds, drive, rho))
    net = drive - c_drag * speeds**2
    spent = np.flatnonzero((net <= 0) & (speeds < top_speed))
    if spent.size:
        k = int(spent[0])
        if k == 0:
            raise ValueError("net_of_drag: the drive does not exceed the drag at standstill")
        w0, w1 = speeds[k - 1] ** 2, speeds[k] ** 2
        top_speed = math.sqrt(w0 + net[k - 1] * (w1 - w0) / (net[k - 1] - net[k]))
    return table_with_top_speed(speeds, net, rho, top_speed)


# --- tum: TUMFTM/global_racetrajectory_optimization -------------------------------------------------------
#: inputs/veh_dyn_info/ggv.csv: v_mps, ax_max_mps2 = ay_max_mps2 (the tyres' limits), every row 12.
TUM_GGV_SPEEDS = (0.0, 4.0, 8.0, 12.0, 16.0, 20.0, 24.0, 28.0, 32.0, 36.0, 40.0, 44.0, 48.0, 52.0, 56.0, 60.0,
                  66.0, 72.0)
TUM_GGV_RHO = (12.0,) * len(TUM_GGV_SPEEDS)
#: inputs/veh_dyn_info/ax_max_machines.csv: v_mps, ax_max_machines_mps2 (the electric machines' limit).
TUM_MACHINE_AX = (5.3, 5.3, 5.3, 5.3, 5.3, 5.3, 5.3, 5.3, 5.3, 5.3, 5.1, 5.0, 4.6, 4.1, 3.7, 2.7, 2.2, 1.5)
#: params/racecar.ini, veh_params: v_max, length, width, mass, curvlim, and dragcoeff
#: ``0.5 rho_air c_w A`` [kg/m], which trajectory_planning_helpers' ``calc_vel_profile`` divides by
#: the mass and subtracts from the machines' and tyres' limit (``ax_max_machines.csv`` is the
#: machines' drive, drag not included).
TUM_V_MAX, TUM_LENGTH, TUM_WIDTH, TUM_MASS, TUM_CURVLIM = 70.0, 4.7, 2.0, 1200.0, 0.12
TUM_DRAG_COEFF = 0.75


def _tum() -> VehicleParams:
    c_drag = TUM_DRAG_COEFF / TUM_MASS
    table = net_of_drag(TUM_GGV_SPEEDS, TUM_MACHINE_AX, TUM_GGV_RHO, c_drag, TUM_V_MAX)
    return VehicleParams.from_table(table, length=TUM_LENGTH, width=TUM_WIDTH, mass=TUM_MASS,
                                    min_turn_radius=1.0 / TUM_CURVLIM, c_drag=c_drag)


# --- av21: the Dallara AV-21 -------------------------------------------------------------------------------
#: The AV-21's figures from the AWSIM racing simulator's vehicle-dynamics page
#: (autonomalabs.github.io/AWSIM, RacingSim/VehicleDynamics): mass [kg], wheelbase and centre of
#: gravity to front axle [m], engine power 473.25 hp [W], drag and front/rear lift coefficients
#: (stated without an area; taken as coefficient times 1 m^2), and the steering motor's range
#: (+-240 deg) over the steering ratio (15).
AV21_MASS, AV21_WHEELBASE, AV21_CG_TO_FRONT = 815.11, 2.9718, 1.6785
AV21_POWER = 473.25 * 745.7
AV21_CD_A, AV21_CLF_A, AV21_CLR_A = 0.8581, 0.65, 1.18
AV21_STEER_MAX = math.radians(240.0 / 15.0)
#: J. Betz et al., "TUM Autonomous Motorsport: An Autonomous Racing Software for the Indy
#: Autonomous Challenge" (arXiv:2205.15979, 2022): peaks of about 270 km/h and 28 m/s^2.
AV21_PEAK_SPEED, AV21_PEAK_ACC = 270.0 / 3.6, 28.0
#: The speeds [m/s] at which the AV-21's drive limit is tabulated.
AV21_SPEEDS = tuple(float(v) for v in range(0, 90, 10))


def av21_figures() -> dict[str, float]:
    """The AV-21's derived figures: downforce per unit mass and speed squared ``downforce``
    [1/m] (front and rear, ``downforce_rear``), the tyres' friction ``mu`` that gives the
    reported peak of 28 m/s^2 at 270 km/h, drag per unit mass ``drag`` [1/m] and the speed
    ``top_speed`` [m/s] where the engine's power equals the drag."""
    half_rho = 0.5 * AIR_DENSITY / AV21_MASS
    downforce = half_rho * (AV21_CLF_A + AV21_CLR_A)
    mu = AV21_PEAK_ACC / (GRAVITY + downforce * AV21_PEAK_SPEED**2)
    drag = half_rho * AV21_CD_A
    return {"downforce": downforce, "downforce_rear": half_rho * AV21_CLR_A, "mu": mu, "drag": drag,
            "top_speed": (AV21_POWER / AV21_MASS / drag) ** (1.0 / 3.0)}


def av21_source_limits(speeds) -> tuple[np.ndarray, np.ndarray]:
    """The AV-21's drive limit and gg radius [m/s^2] at ``speeds`` [m/s]: the gg radius
    ``mu (g + downforce V^2)``; the drive the smaller of the rear tyres' grip (the rear axle's
    static load share and the rear downforce) and the engine's power ``P / (m V)``."""
    fig = av21_figures()
    v = np.asarray(speeds, dtype=float)
    rho = fig["mu"] * (GRAVITY + fig["downforce"] * v**2)
    rear_grip = fig["mu"] * (GRAVITY * AV21_CG_TO_FRONT / AV21_WHEELBASE + fig["downforce_rear"] * v**2)
    with np.errstate(divide="ignore"):
        power = np.where(v > 0, AV21_POWER / AV21_MASS / np.maximum(v, 1e-300), np.inf)
    return np.minimum(rear_grip, power), rho


def _av21() -> VehicleParams:
    ax, rho = av21_source_limits(AV21_SPEEDS)
    figures = av21_figures()
    table = net_of_drag(AV21_SPEEDS, ax, rho, figures["drag"], figures["top_speed"])
    # the footprint: the paper's 4.7 m x 2.0 m (no public figure for the AV-21's was found)
    jerk = float(np.max(table.rho)) / JERK_RISE_TIME
    return VehicleParams.from_table(table, length=4.7, width=2.0, mass=AV21_MASS,
                                    min_turn_radius=AV21_WHEELBASE / math.tan(AV21_STEER_MAX), jx_max=jerk, jy_max=jerk,
                                    c_drag=figures["drag"])


# --- f1tenth: f1tenth/f1tenth_gym ---------------------------------------------------------------------------
#: gym/f110_gym/envs/f110_env.py, the default params: mu, lf, lr, m, s_max, v_switch, a_max, v_max,
#: width, length; gym/f110_gym/envs/dynamic_models.py (accl_constraints): the drive limit is a_max
#: up to v_switch and a_max v_switch / V above it.
F1TENTH_MU, F1TENTH_LF, F1TENTH_LR, F1TENTH_MASS = 1.0489, 0.15875, 0.17145, 3.74
F1TENTH_S_MAX, F1TENTH_V_SWITCH, F1TENTH_A_MAX, F1TENTH_V_MAX = 0.4189, 7.319, 9.51, 20.0
F1TENTH_WIDTH, F1TENTH_LENGTH = 0.31, 0.58
F1TENTH_SPEEDS = (0.0, F1TENTH_V_SWITCH, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0)
#: Jerk limit [m/s^3]: the paper's 30 scaled as a 1:10 model at equal accelerations, whose
#: times are sqrt(10) shorter (no source gives one).
F1TENTH_JERK = 30.0 * math.sqrt(10.0)


def f1tenth_source_limits(speeds) -> tuple[np.ndarray, np.ndarray]:
    """f1tenth_gym's drive limit and gg radius ``mu g`` [m/s^2] at ``speeds`` [m/s]."""
    v = np.asarray(speeds, dtype=float)
    ax = np.where(v > F1TENTH_V_SWITCH, F1TENTH_A_MAX * F1TENTH_V_SWITCH / np.maximum(v, F1TENTH_V_SWITCH),
                  F1TENTH_A_MAX)
    return ax, np.full_like(v, F1TENTH_MU * GRAVITY)


def _f1tenth() -> VehicleParams:
    ax, rho = f1tenth_source_limits(F1TENTH_SPEEDS)
    table = table_with_top_speed(F1TENTH_SPEEDS, ax, rho, F1TENTH_V_MAX)
    return VehicleParams.from_table(
        table, length=F1TENTH_LENGTH, width=F1TENTH_WIDTH, mass=F1TENTH_MASS,
        min_turn_radius=(F1TENTH_LF + F1TENTH_LR) / math.tan(F1TENTH_S_MAX),
        jx_max=F1TENTH_JERK, jy_max=F1TENTH_JERK)


_TUM_SOURCE = ("TUMFTM/global_racetrajectory_optimization: inputs/veh_dyn_info/ggv.csv (tyres: 12 m/s^2 "
               "longitudinal and lateral, 0-72 m/s), inputs/veh_dyn_info/ax_max_machines.csv (drive 5.3 m/s^2 "
               "falling to 1.5 m/s^2 at 72 m/s), params/racecar.ini (v_max 70 m/s, 4.7 m x 2.0 m, 1200 kg, "
               "curvature limit 0.12 1/m, drag coefficient 0.75 kg/m)")
_AV21_SOURCE = ("AWSIM racing simulator, RacingSim/VehicleDynamics (autonomalabs.github.io/AWSIM): 815.11 kg, "
                "wheelbase 2.9718 m, 473.25 hp, drag 0.8581 and lift 0.65 + 1.18 coefficients, steering 240 deg / 15; "
                "J. Betz et al., arXiv:2205.15979 (2022): 28 m/s^2 at 270 km/h")
_F1TENTH_SOURCE = ("f1tenth/f1tenth_gym: gym/f110_gym/envs/f110_env.py (default params: mu 1.0489, a_max 9.51 m/s^2, "
                   "v_switch 7.319 m/s, v_max 20 m/s, 0.58 m x 0.31 m, 3.74 kg, wheelbase 0.3302 m, steering "
                   "0.4189 rad), gym/f110_gym/envs/dynamic_models.py (drive a_max v_switch / V above v_switch)")

_av21_ax, _av21_rho = av21_source_limits(AV21_SPEEDS)
_f1_ax, _f1_rho = f1tenth_source_limits(F1TENTH_SPEEDS)

#: The classes by name, slowest at full scale first: what ``--car`` takes.
CAR_CLASSES: dict[str, CarClass] = {
    c.name: c for c in (
        CarClass("paper", "the paper's car (M. Rowold, arXiv:2310.00766): 25 m/s, gg radius 12 m/s^2 plus downforce",
                 "M. Rowold, arXiv:2310.00766 (the formula's figures); turning radius and mass: this project",
                 VehicleParams),
        CarClass("tum", "TUM's research car (TUMFTM global_racetrajectory_optimization): 62.8 m/s with drag, 12 m/s^2",
                 _TUM_SOURCE, _tum, TUM_GGV_SPEEDS, TUM_MACHINE_AX, TUM_GGV_RHO),
        CarClass("av21", "Dallara AV-21 of the Indy Autonomous Challenge: open-wheel, 88 m/s, downforce",
                 _AV21_SOURCE, _av21, AV21_SPEEDS, tuple(_av21_ax.tolist()), tuple(_av21_rho.tolist())),
        CarClass("f1tenth", "the 1:10-scale F1TENTH car (f1tenth_gym): 20 m/s, 0.58 m long",
                 _F1TENTH_SOURCE, _f1tenth, F1TENTH_SPEEDS, tuple(_f1_ax.tolist()), tuple(_f1_rho.tolist())),
    )
}


def car_names() -> list[str]:
    """The names :func:`get_car` takes."""
    return list(CAR_CLASSES)


def get_car(name: str) -> VehicleParams:
    """The :class:`VehicleParams` of class ``name`` (one of :func:`car_names`, any case).

    Raises:
        ValueError: for another name, listing the classes.
    """
    if not isinstance(name, str) or name.strip().lower() not in CAR_CLASSES:
        raise ValueError(f"unknown car class {name!r}: the classes are {car_names()}")
    return CAR_CLASSES[name.strip().lower()].vehicle()


#: The fields of a car that, with its limit curves, say which class it is (:func:`class_of`).
_IDENTITY_FIELDS = ("length", "width", "v_max", "jx_max", "jy_max", "min_turn_radius", "mass", "c_drag")


def class_of(vehicle: VehicleParams) -> str | None:
    """The name of the class ``vehicle`` (one car, e.g. ``game.vehicles.car(i)``) is a car of,
    or None for a car of none: its numbers (:data:`_IDENTITY_FIELDS`) and its drive limit and
    gg radius at the class's table speeds and top speed all equal the class's, to a relative
    1e-9 (a car stacked with others has its curve on more speeds, whose values lie on it)."""
    for name, car_class in CAR_CLASSES.items():
        car = car_class.vehicle()
        if not all(np.isclose(float(np.asarray(getattr(vehicle, field))), float(np.asarray(getattr(car, field))),
                              rtol=1e-9, atol=0.0) for field in _IDENTITY_FIELDS):
            continue
        speeds = np.append(np.asarray(car.as_table().table.speeds, dtype=float), float(car.v_max))
        if all(np.allclose(np.asarray(curve(vehicle), dtype=float), np.asarray(curve(car), dtype=float),
                           rtol=1e-9, atol=1e-12)
               for curve in (lambda c: c.ax_max(speeds), lambda c: c.rho(speeds))):
            return name
    return None
