"""Replays: a recorded race drawn again, to a GIF or an MP4, without racing it again.

Tournaments and sweeps keep every race's :class:`Replay` in ``replays/race-KKKKK.npz``
beside ``results.jsonl`` (``K``: the race's index in the run's schedule; its record says
``"race": K`` and ``"replay": "replays/race-KKKKK.npz"``). A replay holds what the frames of
the race show, step by step: the joint states ``(T+1, N, 6)`` (float64, as raced), each
car's status and position, the agents' names and, when the run was asked to keep them
(``--plans``), what each planner planned and expected of the others at every step, with
what is needed to draw them (the track, the cars' sizes, the race's length). Frames drawn
from a replay equal the frames drawn while the race ran (``tests/test_replay.py``).

``racing replay RUN_DIR --race K`` renders one; ``racing replay RUN_DIR`` lists them.
Guide: docs/viewing.md.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from experiments.files import replace_atomically
from experiments.race import incident_notes
from racing_env.render import Renderer, Scene, save_video
from racing_env.track import Track, get_track

REPLAYS = "replays"
"""The folder of a run's replays, beside its ``results.jsonl``."""

_TRACK_ARRAYS = ("s", "kappa", "width_left", "width_right", "x", "y", "heading")


def replay_file(race: int) -> str:
    """The replay of race ``race`` (its index in the run's schedule), relative to the run folder."""
    return f"{REPLAYS}/race-{race:05d}.npz"


@dataclasses.dataclass
class CarSizes:
    """Per-car footprint ``length`` and ``width`` ``(N,)`` [m], what frames need of the cars."""

    length: np.ndarray
    width: np.ndarray


@dataclasses.dataclass
class Replay:
    """A recorded race, as its frames show it.

    Attributes:
        xs: joint states ``(T+1, N, 6)`` float64, the start included.
        status: ``(T+1, N)`` int8 (:data:`racing_env.render.RACING`, ``FINISHED``, ``RETIRED``).
        position: ``(T+1, N)`` int16 race positions, 1 = leading.
        labels: the agents' names, one per car.
        dt: time step [s].
        track: the track: a built-in name or a CSV path (as the run gave it), or the
            :class:`racing_env.Track` itself.
        cars: the cars' footprints.
        laps: laps of a race over laps, else None (a race over a distance).
        finish_s: the finish line's arc length [m].
        plans: None, or ``(T+1, N, H, N, 2)`` float32 ``[s, n]``: what car ``i`` planned at
            step ``k`` is ``plans[k, i]``, rows of NaN where its plan is shorter than ``H``
            or it had none (:attr:`racing_env.render.Scene.plans`).
        race: the race's index in its run's schedule (None outside a run); ``id``: its job id.
        incidents: the race's contact incidents (:attr:`experiments.race.RaceRecord.incidents`),
            whose verdicts the frames show for a few seconds after each began.
    """

    xs: np.ndarray
    status: np.ndarray
    position: np.ndarray
    labels: tuple[str, ...]
    dt: float
    track: str | Track
    cars: CarSizes
    laps: int | None
    finish_s: float
    plans: np.ndarray | None = None
    race: int | None = None
    id: str | None = None
    incidents: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    @property
    def steps(self) -> int:
        """Env steps the race took (``T``)."""
        return self.xs.shape[0] - 1

    def scene(self, k: int) -> Scene:
        """What the frame of step ``k`` shows."""
        plans = None
        if self.plans is not None:
            plans = []
            for plan in self.plans[k]:
                rows = ~np.isnan(plan[:, 0, 0])
                plans.append(plan[rows] if rows.any() else None)
        return Scene(x=self.xs[k], time=k * self.dt, status=self.status[k], position=self.position[k],
                     labels=self.labels, plans=plans, notes=incident_notes(self.incidents, k, self.labels, self.dt))

    def renderer(self, size: int = 480, camera: str = "auto", plans: bool = True) -> Renderer:
        """A renderer of this race's track, cars and length."""
        track = self.track if isinstance(self.track, Track) else get_track(self.track)
        return Renderer(track, self.cars, size=size, camera=camera, plans=plans, laps=self.laps,
                        finish_s=self.finish_s)

    def frames(self, every: int = 3, size: int = 480, camera: str = "auto", plans: bool = True,
               renderer: Renderer | None = None) -> list[np.ndarray]:
        """Frames of every ``every``-th step and of the last state, ``uint8 (size, size, 3)``
        each (the steps a race run with ``render_every=every`` draws)."""
        if every < 1:
            raise ValueError(f"every must be a number of steps >= 1, got {every!r}")
        renderer = renderer or self.renderer(size, camera, plans)
        steps = list(range(0, self.steps + 1, every))
        if steps[-1] != self.steps:
            steps.append(self.steps)
        return [renderer.draw(self.scene(k)) for k in steps]


def expectation_gaps(replay: Replay) -> np.ndarray:
    """How far what each planner expects of another car is from that car's own plan,
    ``(T+1, N, N)`` [m]: entry ``[k, i, j]`` is the largest distance in the ``(s, n)`` plane,
    over the steps both plans cover, between car ``i``'s prediction of car ``j`` and car
    ``j``'s own plan, both made at step ``k``. NaN where either car had no plan, and on the
    diagonal. Two game planners that solved the same equilibrium agree (about 0); an iLQR
    planner's constant-velocity prediction does not. Needs a replay with plans."""
    if replay.plans is None:
        raise ValueError("the replay has no plans: run the tournament or sweep with --plans")
    plans = replay.plans.astype(np.float64)  # (T+1, N, H, N, 2)
    steps, num = plans.shape[:2]
    gaps = np.full((steps, num, num), np.nan)
    for i in range(num):
        for j in range(num):
            if i != j:
                distance = np.hypot(*np.moveaxis(plans[:, i, :, j] - plans[:, j, :, j], -1, 0))  # (T+1, H)
                covered = ~np.isnan(distance)
                gaps[:, i, j] = np.where(covered.any(axis=1), np.nanmax(np.where(covered, distance, -np.inf),
                                                                          axis=1), np.nan)
    return gaps


def replay_of(record: Any, env: Any, race: int | None = None, id: str | None = None) -> Replay:
    """The replay of ``record`` (:class:`experiments.race.RaceRecord`), raced in ``env``
    (:class:`racing_env.RacingParallelEnv`)."""
    num = env.num_cars
    vehicles = env.game.vehicles
    cars = CarSizes(length=np.broadcast_to(np.asarray(vehicles.length, float), (num,)).copy(),
                    width=np.broadcast_to(np.asarray(vehicles.width, float), (num,)).copy())
    track = env.config.track
    if not isinstance(track, Track) and os.path.isfile(os.fspath(track)):
        track = os.path.abspath(track)  # a CSV file: found again from any working folder
    return Replay(xs=np.asarray(record.xs, dtype=np.float64), status=np.asarray(record.status, np.int8),
                  position=np.asarray(record.position, np.int16), labels=tuple(record.labels), dt=float(record.dt),
                  track=track, cars=cars, laps=env.race_laps, finish_s=float(env.finish_s),
                  plans=None if record.plans is None else pad_plans(record.plans, num), race=race, id=id,
                  incidents=list(record.incidents))


def pad_plans(plans: Sequence[Sequence[np.ndarray | None]], num: int) -> np.ndarray:
    """Per-step, per-car plans (None or ``(H_k, N, 2)``) as one ``(T+1, N, H, N, 2)`` float32
    array, padded with NaN rows to the longest plan ``H``."""
    longest = max((plan.shape[0] for row in plans for plan in row if plan is not None), default=1)
    out = np.full((len(plans), num, longest, num, 2), np.nan, dtype=np.float32)
    for k, row in enumerate(plans):
        for i, plan in enumerate(row):
            if plan is not None:
                out[k, i, : plan.shape[0]] = plan
    return out


def save_replay(replay: Replay, path: Path) -> Path:
    """Write ``replay`` as a compressed ``.npz`` (replacing the file whole, never in part)."""
    meta = {"labels": list(replay.labels), "dt": replay.dt, "laps": replay.laps, "finish_s": replay.finish_s,
            "race": replay.race, "id": replay.id, "incidents": replay.incidents, "version": 1}
    arrays = {"xs": replay.xs, "status": replay.status, "position": replay.position,
              "car_length": replay.cars.length, "car_width": replay.cars.width}
    if isinstance(replay.track, Track):
        arrays.update({f"track_{name}": getattr(replay.track, name) for name in _TRACK_ARRAYS})
        meta["track"] = {"length": replay.track.length, "closed": replay.track.closed, "name": replay.track.name}
    else:
        meta["track"] = os.fspath(replay.track)
    if replay.plans is not None:
        arrays["plans"] = replay.plans
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def write(partial: Path) -> None:
        with open(partial, "wb") as sink:
            np.savez_compressed(sink, meta=np.array(json.dumps(meta)), **arrays)

    replace_atomically(write, path)
    return path


def load_replay(path: Path) -> Replay:
    """The replay in ``path`` (written by :func:`save_replay`)."""
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        track = meta["track"]
        if isinstance(track, dict):
            track = Track(**{name: data[f"track_{name}"] for name in _TRACK_ARRAYS}, **track)
        return Replay(xs=data["xs"], status=data["status"], position=data["position"],
                      labels=tuple(meta["labels"]), dt=float(meta["dt"]), track=track,
                      cars=CarSizes(length=data["car_length"], width=data["car_width"]), laps=meta["laps"],
                      finish_s=float(meta["finish_s"]), plans=data["plans"] if "plans" in data else None,
                      race=meta["race"], id=meta["id"], incidents=meta.get("incidents", []))


def recorded_races(out: Path) -> list[dict[str, Any]]:
    """The races of run folder ``out`` that have a replay, in schedule order: each
    ``{"race": K, "id", "path", "record"}`` (``record``: its line in ``results.jsonl``)."""
    from experiments.jsonl import read_jsonl

    records = {r.get("race"): r for r in read_jsonl(Path(out) / "results.jsonl") if r.get("race") is not None}
    races = []
    for path in sorted((Path(out) / REPLAYS).glob("race-*.npz")):
        race = int(path.stem.split("-")[1])
        if race in records:  # a replay without its record is of a race that was cut short: it is raced again
            races.append({"race": race, "id": records[race]["id"], "path": path, "record": records[race]})
    return races


def render_race(out: Path, race: int, path: Path, *, every: int = 3, size: int = 480, camera: str = "auto",
                plans: bool = True, steps: Sequence[int] | None = None) -> Path:
    """Render race ``race`` (its schedule index) of run folder ``out`` to ``path``: a
    ``.gif`` or ``.mp4`` of every ``every``-th step, playing in race time, or with ``steps``
    a ``.png`` of the frames of those steps side by side. Returns ``path``.

    Raises FileNotFoundError when the run holds no replay of that race."""
    file = Path(out) / replay_file(race)
    if not file.exists():
        known = [r["race"] for r in recorded_races(out)]
        hint = f"recorded races: {known}" if known else (
            "the run recorded no replay (runs written before replays existed have none)")
        raise FileNotFoundError(f"no replay of race {race} in {out}; {hint}")
    replay = load_replay(file)
    if steps is not None:
        return save_strip(replay, steps, Path(path), size=size, camera=camera, plans=plans)
    if Path(path).suffix.lower() == ".png":
        raise ValueError("a .png holds chosen steps (--steps K,...); a whole race is a .gif or .mp4")
    frames = replay.frames(every=every, size=size, camera=camera, plans=plans)
    return save_video(frames, path, fps=1.0 / (every * replay.dt))


def save_strip(replay: Replay, steps: Sequence[int], path: Path, size: int = 480, camera: str = "auto",
               plans: bool = True) -> Path:
    """The frames of ``steps`` of ``replay`` side by side (4 px apart) as a PNG at ``path``."""
    from PIL import Image

    if path.suffix.lower() != ".png":
        raise ValueError(f"frames of chosen steps are written as a .png, got {path.name!r}")
    bad = [k for k in steps if isinstance(k, bool) or not 0 <= k <= replay.steps]
    if not steps or bad:
        raise ValueError(f"steps must be step indices in [0, {replay.steps}] (the race's steps), got {list(steps)}")
    renderer = replay.renderer(size, camera, plans)
    strip = Image.new("RGB", (len(steps) * (size + 4) - 4, size), (255, 255, 255))
    for n, k in enumerate(steps):
        strip.paste(Image.fromarray(renderer.draw(replay.scene(k))), (n * (size + 4), 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    strip.save(path)
    return path


def print_races(out: Path) -> None:
    """Print the recorded races of run folder ``out``: index, id, finishing order, steps,
    whether the planners' plans were kept."""
    from rich.console import Console
    from rich.table import Table

    console = Console(width=160)
    races = recorded_races(out)
    if not races:
        console.print(f"{out} holds no recorded race (runs written before replays existed have none)")
        return
    table = Table(title=f"recorded races in {out} (racing replay {out} --race K)")
    for column in ("K", "id", "order (winner first)", "steps", "plans"):
        table.add_column(column, overflow="fold")
    for race in races:
        record = race["record"]
        order = record.get("order") or [car["agent"] for car in sorted(record["agents"], key=lambda c: c["place"])]
        with np.load(race["path"]) as data:
            plans = "plans" in data.files
        table.add_row(str(race["race"]), race["id"], " > ".join(order), str(record["steps"]), "yes" if plans else "no")
    console.print(table)
