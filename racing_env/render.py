"""Drawing a race: top-down frames (uint8 RGB), trajectory plots, GIF and MP4 export.

A frame shows a :class:`Scene`: the joint state and, when known, each car's status and
race position, its agent's name and what its planner expects (its plan and its prediction
of every other car). :class:`Renderer` draws scenes with Pillow:

- **Cameras.** ``follow`` keeps the cars still racing in a window that zooms with their
  spread (:func:`follow_view`; in a field of more than :data:`FOLLOW_CARS` cars, or with
  ``follow_car``, the pack around the leader or that car) and shows the whole circuit as an
  inset map; ``track``
  shows the whole circuit; ``auto`` (the default) follows a field of up to
  :data:`FOLLOW_CARS` cars and shows a bigger one whole where the circuit fits in
  :data:`TRACK_VIEW_MAX` metres.
- **Labels and heads-up lines**: each car is tagged with its label (the agent's name),
  and a box in the top-left corner gives the time, the leader's lap (or distance) and, per
  car in race order, its position, speed and gap to the leader [m] (with three cars or more
  also the interval to the car ahead, in brackets).
- **Plans** (``plans=True``): a car's own plan as a long-dashed line and its prediction of
  each other car as a short-dashed line, both in the planning car's colour, so whose
  expectation it is reads from the colour and whose trajectory from where it starts.

A frame is a pure function of the scene and the renderer's settings, so a race drawn
again from its recorded scenes (``experiments.replay``) gives the same frames. Drawing
costs a few milliseconds (docs/performance.md, "Rendering (`racing bench --only render`)"). Plots use matplotlib.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from racing_env.dynamics import CHI, N_LAT, S, V
from racing_env.track import Track

CAR_COLOURS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
    (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127),
]
GRASS, ASPHALT, LINE = (96, 140, 80), (70, 70, 74), (235, 235, 235)
PANEL, PANEL_TEXT, GHOST = (24, 24, 28), (240, 240, 240), (200, 200, 200)
NOTE_TEXT = (255, 190, 60)
CAMERAS = ("auto", "follow", "track")
FOLLOW_CARS = 4  # ``auto`` follows fields of at most this many cars
TRACK_VIEW_MAX = 600.0  # [m] ``auto`` shows a bigger field whole on circuits at most this big
FOLLOW_MIN_SPAN = 60.0  # [m] the follow window's side when the cars are close together
FOLLOW_MAX_SPAN = 240.0  # [m] its widest: cars further apart than that, it follows the leader
FOLLOW_MARGIN = 40.0  # [m] added to 1.5 x the cars' spread
INSET_SHARE = 0.3  # the inset map's side as a share of the frame's

RACING, FINISHED, RETIRED = 0, 1, 2
"""A car's status in a :class:`Scene`: still racing, finished, or retired by an incident rule."""


def car_status(finished: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Each car's :data:`RACING` / :data:`FINISHED` / :data:`RETIRED` status ``(N,)`` int8
    from the env's ``finished`` and ``out`` (retired) flags ``(N,)``."""
    return np.where(np.asarray(out, bool), RETIRED, np.where(np.asarray(finished, bool), FINISHED, RACING)).astype(np.int8)


def car_colour(index: int) -> tuple[int, int, int]:
    return CAR_COLOURS[index % len(CAR_COLOURS)]


@dataclasses.dataclass(frozen=True)
class Scene:
    """What one frame shows.

    Attributes:
        x: joint state ``(N, 6)`` = ``[s, V, n, chi, ax, ay]`` per car.
        time: race time [s] (None: not shown).
        status: ``(N,)`` :data:`RACING`, :data:`FINISHED` or :data:`RETIRED` (None: all racing).
        position: ``(N,)`` race positions, 1 = leading (None: by arc length ``s``).
        labels: a name per car (None: ``car_i``).
        plans: per car, None or its plan ``(H, N, 2)`` of ``[s, n]`` [m]: row ``i`` the
            car's own plan, the other rows its prediction of the other cars.
        notes: lines shown in a panel at the frame's foot (the steward's verdicts).
    """

    x: np.ndarray
    time: float | None = None
    status: np.ndarray | None = None
    position: np.ndarray | None = None
    labels: Sequence[str] | None = None
    plans: Sequence[np.ndarray | None] | None = None
    notes: Sequence[str] | None = None


def car_polygons(track: Track, x: np.ndarray, vehicles: Any) -> np.ndarray:
    """World corners of every car footprint, ``(N, 4, 2)`` [m]. ``vehicles``: anything with
    per-car (or shared) ``length`` and ``width`` [m], e.g. :class:`racing_env.VehicleParams`."""
    cx, cy, heading = track.to_cartesian(x[:, S], x[:, N_LAT])
    yaw = heading + x[:, CHI]
    half_l = 0.5 * np.broadcast_to(np.asarray(vehicles.length, dtype=float), x.shape[:1])[:, None]
    half_w = 0.5 * np.broadcast_to(np.asarray(vehicles.width, dtype=float), x.shape[:1])[:, None]
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float)
    lx, ly = local[None, :, 0] * half_l, local[None, :, 1] * half_w
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([cx[:, None] + c * lx - s * ly, cy[:, None] + s * lx + c * ly], axis=-1)


def follow_view(xy: np.ndarray, racing: np.ndarray, leader: int, focus: int | None = None
                ) -> tuple[np.ndarray, float]:
    """The follow camera's window: ``(centre (2,), side)`` [m] for car positions ``xy (N, 2)``.

    The window holds the cars still ``racing (N,)`` (all cars once none is) with a margin:
    its side is ``1.5 x`` their spread plus :data:`FOLLOW_MARGIN`, at least
    :data:`FOLLOW_MIN_SPAN`. Wider than :data:`FOLLOW_MAX_SPAN`, it stays at that side
    centred on the ``leader``'s car: the others are on the inset map. With ``focus`` (a car
    index) it holds the pack around that car instead: the cars within half of
    :data:`FOLLOW_MAX_SPAN` of it (the car itself whether racing or not).
    """
    if focus is not None:
        near = np.hypot(*(xy - xy[focus]).T) <= 0.5 * FOLLOW_MAX_SPAN
        racing = (np.asarray(racing) & near) | (np.arange(xy.shape[0]) == focus)
        leader = focus
    points = xy[racing] if np.any(racing) else xy
    lo, hi = points.min(axis=0), points.max(axis=0)
    side = 1.5 * float(np.max(hi - lo)) + FOLLOW_MARGIN
    if side > FOLLOW_MAX_SPAN:
        return xy[leader].astype(float), FOLLOW_MAX_SPAN
    return 0.5 * (lo + hi), max(side, FOLLOW_MIN_SPAN)


def _runs(mask: np.ndarray, closed: bool) -> list[np.ndarray]:
    """Index arrays of the runs of True in ``mask``; on a closed track a run may wrap."""
    if mask.all():
        return [np.arange(len(mask) + (1 if closed else 0)) % len(mask)]
    edges = np.flatnonzero(np.diff(np.concatenate([[False], mask, [False]]).astype(np.int8)))
    runs = [np.arange(a, b) for a, b in zip(edges[::2], edges[1::2])]
    if closed and len(runs) > 1 and mask[0] and mask[-1]:  # the run over the start line joins
        runs = [np.concatenate([runs[-1], runs[0]])] + runs[1:-1]
    return runs


def _font(size: int) -> ImageFont.ImageFont:
    return ImageFont.load_default(size=size)


class Renderer:
    """Top-down frames of a race on ``track``.

    Args:
        track: the race's track.
        vehicles: per-car ``length`` and ``width`` [m] (a :class:`racing_env.VehicleParams`).
        size: side of the square frame [px].
        camera: one of :data:`CAMERAS` (module docstring).
        plans: draw the scenes' plans and predictions.
        laps: the race's laps (the heads-up line shows the leader's lap of them), or None
            for a race over a distance.
        finish_s: the finish line's arc length [m] (shown as distance when ``laps`` is None).
        follow_car: the car the follow camera holds with the pack around it
            (:func:`follow_view`'s ``focus``); None: in a field of more than
            :data:`FOLLOW_CARS` cars the pack around the leader, else every car racing.
    """

    def __init__(self, track: Track, vehicles: Any, size: int = 512, camera: str = "auto", *,
                 plans: bool = True, laps: int | None = None, finish_s: float | None = None,
                 follow_car: int | None = None):
        if camera not in CAMERAS:
            raise ValueError(f"camera must be one of {list(CAMERAS)}, got {camera!r}")
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 32 <= size <= 4096:
            raise ValueError(f"the frame size must be a number of pixels in [32, 4096], got {size!r}")
        self.track, self.vehicles, self.size = track, vehicles, int(size)
        self.plans, self.laps, self.finish_s = bool(plans), laps, finish_s
        self._left, self._right = track.boundaries()
        pts = np.concatenate([self._left, self._right])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        self._extent = float(np.max(hi - lo))
        self._track_view = (0.5 * (lo + hi), 1.08 * self._extent)
        # longest boundary segment [m]: a segment with an end this far outside the window may cross it
        steps = np.concatenate([np.diff(self._left, axis=0), np.diff(self._right, axis=0)])
        self._reach = float(np.max(np.hypot(steps[:, 0], steps[:, 1]))) if len(steps) else 0.0
        self.camera = camera
        self.follow_car = follow_car
        self._fonts = {k: _font(max(9, round(self.size * k / 512))) for k in (11, 13)}
        self._whole_track: Image.Image | None = None
        self._inset: tuple[Image.Image, np.ndarray, float, int] | None = None
        self._figure = None

    # --- geometry -------------------------------------------------------------------------
    def _to_px(self, xy: np.ndarray, centre: np.ndarray, span: float) -> np.ndarray:
        scale = self.size / span
        px = (xy[..., 0] - centre[0]) * scale + 0.5 * self.size
        py = 0.5 * self.size - (xy[..., 1] - centre[1]) * scale
        return np.stack([px, py], axis=-1)

    def camera_for(self, num_cars: int) -> str:
        """The camera a race of ``num_cars`` cars is drawn with (``auto`` resolved)."""
        if self.camera != "auto":
            return self.camera
        return "follow" if num_cars <= FOLLOW_CARS or self._extent > TRACK_VIEW_MAX else "track"

    def view(self, scene: Scene) -> tuple[np.ndarray, float]:
        """The window a scene is drawn in: ``(centre (2,), side)`` [m]."""
        if self.camera_for(scene.x.shape[0]) == "track":
            return self._track_view
        x = scene.x
        cx, cy, _ = self.track.to_cartesian(x[:, S], x[:, N_LAT])
        racing = np.ones(x.shape[0], bool) if scene.status is None else np.asarray(scene.status) == RACING
        candidates = np.flatnonzero(racing) if racing.any() else np.arange(x.shape[0])
        leader = int(candidates[np.argmax(x[candidates, S])])
        focus = self.follow_car if self.follow_car is not None else (leader if x.shape[0] > FOLLOW_CARS else None)
        return follow_view(np.stack([cx, cy], axis=-1), racing, leader, focus)

    # --- the track ------------------------------------------------------------------------
    def _draw_track(self, draw: ImageDraw.ImageDraw, centre: np.ndarray, span: float) -> None:
        """The asphalt, its edges and the start line of the part of the track in the window."""
        half = 0.5 * span + self._reach
        inside = (np.all(np.abs(self._left - centre) <= half, axis=1)
                  | np.all(np.abs(self._right - centre) <= half, axis=1))
        # each visible point with its neighbours, so that segments crossing the window's edge are drawn
        mask = inside | np.roll(inside, 1) | np.roll(inside, -1)
        if not self.track.closed:
            mask[0], mask[-1] = inside[:2].any(), inside[-2:].any()
        if not mask.any():
            return
        width = max(1, round(0.15 * self.size / span))
        left, right = self._to_px(self._left, centre, span), self._to_px(self._right, centre, span)
        for run in _runs(mask, self.track.closed):
            outline = np.concatenate([left[run], right[run][::-1]])
            draw.polygon([tuple(p) for p in outline], fill=ASPHALT)
            for edge in (left[run], right[run]):
                draw.line([tuple(p) for p in edge], fill=LINE, width=width)
        if mask[0]:
            draw.line([tuple(left[0]), tuple(right[0])], fill=(250, 250, 250), width=3 * width)

    def _background(self) -> Image.Image:
        """The whole track, drawn once (camera ``track``)."""
        if self._whole_track is None:
            self._whole_track = Image.new("RGB", (self.size, self.size), GRASS)
            self._draw_track(ImageDraw.Draw(self._whole_track), *self._track_view)
        return self._whole_track

    def _inset_map(self) -> tuple[Image.Image, np.ndarray, float, int]:
        """The inset map's image (drawn once), its centre and span [m] and side [px]."""
        if self._inset is None:
            side = max(48, round(INSET_SHARE * self.size))
            centre, span = self._track_view
            scale = side / span
            image = Image.new("RGB", (side, side), PANEL)
            draw = ImageDraw.Draw(image)
            cx, cy, _ = self.track.to_cartesian(np.asarray(self.track.s), 0.0)
            line = np.stack([(cx - centre[0]) * scale + 0.5 * side, 0.5 * side - (cy - centre[1]) * scale], axis=-1)
            points = [tuple(p) for p in line] + ([tuple(line[0])] if self.track.closed else [])
            draw.line(points, fill=(150, 150, 150), width=max(1, side // 60))
            draw.rectangle([0, 0, side - 1, side - 1], outline=(90, 90, 90))
            self._inset = (image, centre, span, side)
        return self._inset

    # --- a frame --------------------------------------------------------------------------
    def draw(self, scene: Scene) -> np.ndarray:
        """The frame of ``scene`` as ``uint8 (size, size, 3)``."""
        x = np.asarray(scene.x, dtype=float)
        camera = self.camera_for(x.shape[0])
        centre, span = self.view(scene)
        if camera == "track":
            image = self._background().copy()
        else:
            image = Image.new("RGB", (self.size, self.size), GRASS)
            self._draw_track(ImageDraw.Draw(image), centre, span)
        draw = ImageDraw.Draw(image)
        status = np.zeros(x.shape[0], int) if scene.status is None else np.asarray(scene.status)
        if self.plans and scene.plans is not None:
            self._draw_plans(draw, scene.plans, centre, span)
        corners = self._to_px(car_polygons(self.track, x, self.vehicles), centre, span)
        for i, quad in enumerate(corners):
            colour = car_colour(i) if status[i] == RACING else GHOST
            mid = quad.mean(axis=0)  # a car is never drawn smaller than 4 px, so it stays visible
            quad = mid + (quad - mid) * max(1.0, 4.0 / max(np.ptp(quad[:, 0]), 1e-6))
            draw.polygon([tuple(p) for p in quad], fill=colour, outline=(0, 0, 0))
        labels = self._labels(scene)
        for i, quad in enumerate(corners):
            self._tag(draw, labels[i], quad, car_colour(i))
        self._heads_up(draw, scene, labels, status)
        if scene.notes:
            self._notes(draw, scene.notes)
        if camera == "follow":
            self._paste_inset(image, x, status, centre, span)
        return np.asarray(image, dtype=np.uint8)

    def frame(self, x: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        """A frame of the joint state ``x (N, 6)`` alone (``active (N,)``: which cars still
        race), as ``uint8 (size, size, 3)``."""
        status = None if active is None else np.where(np.asarray(active, bool), RACING, FINISHED)
        return self.draw(Scene(x=np.asarray(x, dtype=float), status=status))

    def _labels(self, scene: Scene) -> list[str]:
        num = scene.x.shape[0]
        labels = [f"car_{i}" for i in range(num)] if scene.labels is None else [str(a) for a in scene.labels]
        return [label if len(label) <= 24 else label[:23] + "…" for label in labels]

    def _tag(self, draw: ImageDraw.ImageDraw, label: str, quad: np.ndarray, colour: tuple[int, int, int]) -> None:
        """The car's label in a box of its colour just above its footprint."""
        if not label:
            return
        font = self._fonts[11]
        left, top, right, bottom = draw.textbbox((0, 0), label, font=font)
        w, h = right - left + 6, bottom - top + 4
        x0 = float(np.clip(quad[:, 0].mean() - 0.5 * w, 0, self.size - w))
        y0 = float(np.clip(quad[:, 1].min() - h - 4, 0, self.size - h))
        draw.rectangle([x0, y0, x0 + w, y0 + h], fill=colour)
        draw.text((x0 + 3 - left, y0 + 2 - top), label, font=font, fill=(255, 255, 255))

    def _heads_up(self, draw: ImageDraw.ImageDraw, scene: Scene, labels: list[str], status: np.ndarray) -> None:
        """Time and the leader's lap (or distance), then per car in race order: position,
        speed and gap to the leader [m] (or that it finished or retired)."""
        x = scene.x
        order = (np.argsort(-x[:, S], kind="stable") if scene.position is None
                 else np.argsort(np.asarray(scene.position), kind="stable"))
        lead = int(order[0])
        header = [] if scene.time is None else [f"t {scene.time:6.1f} s"]
        if self.laps is not None and self.track.closed:
            lap = min(int(np.floor(max(x[lead, S], 0.0) / self.track.length)) + 1, self.laps)
            header.append(f"lap {lap}/{self.laps}")
        elif self.finish_s is not None:
            header.append(f"{max(x[lead, S], 0.0):.0f}/{self.finish_s:.0f} m")
        lines = [("  ".join(header), PANEL_TEXT)] if header else []
        field = x.shape[0] > 2
        for place, i in enumerate(order, 1):
            state = {FINISHED: "finished", RETIRED: "out"}.get(int(status[i]))
            gap = "" if place == 1 else f"+{x[lead, S] - x[i, S]:.1f} m"
            if field and place > 2:  # and the interval to the car ahead
                gap += f" ({x[order[place - 2], S] - x[i, S]:+.1f})"
            lines.append((f"P{place} {labels[i] or f'car_{i}'}  {x[i, V]:4.1f} m/s  {state or gap}", car_colour(i)))
        font = self._fonts[13] if x.shape[0] <= 10 else self._fonts[11]
        height = font.size + 4
        width = max(draw.textlength(text, font=font) for text, _ in lines) + 16
        draw.rectangle([0, 0, width, height * len(lines) + 6], fill=PANEL)
        for k, (text, colour) in enumerate(lines):
            y = 4 + k * height
            if k or not header:  # a swatch of the car's colour before its line
                draw.rectangle([4, y + 3, 8, y + height - 3], fill=colour)
            draw.text((12 if (k or not header) else 6, y), text, font=font, fill=PANEL_TEXT)

    def _notes(self, draw: ImageDraw.ImageDraw, notes: Sequence[str]) -> None:
        """``notes`` in a panel at the frame's foot, one per line, in the steward's amber."""
        font = self._fonts[11]
        height = font.size + 4
        width = min(max(draw.textlength(text, font=font) for text in notes) + 12, self.size)
        top = self.size - height * len(notes) - 6
        draw.rectangle([0, top, width, self.size], fill=PANEL)
        for k, text in enumerate(notes):
            draw.text((6, top + 3 + k * height), text, font=font, fill=NOTE_TEXT)

    def _draw_plans(self, draw: ImageDraw.ImageDraw, plans: Sequence[np.ndarray | None], centre: np.ndarray,
                    span: float) -> None:
        """Each car's plan (long dashes, 3 px) and predictions of the others (short dashes,
        2 px, with a ring where they end) in the planning car's colour."""
        for i, plan in enumerate(plans):
            if plan is None:
                continue
            plan = np.asarray(plan, dtype=float)
            px_x, px_y, _ = self.track.to_cartesian(plan[..., 0], plan[..., 1])
            points = self._to_px(np.stack([px_x, px_y], axis=-1), centre, span)  # (H, N, 2)
            colour = car_colour(i)
            for j in range(points.shape[1]):
                line = points[:, j]
                own = j == i
                period, on, width = (3, 2, 3) if own else (2, 1, 2)
                for k in range(line.shape[0] - 1):
                    if k % period < on:
                        draw.line([tuple(line[k]), tuple(line[k + 1])], fill=colour, width=width)
                if not own:
                    ex, ey = line[-1]
                    draw.ellipse([ex - 2, ey - 2, ex + 2, ey + 2], outline=colour)

    def _paste_inset(self, image: Image.Image, x: np.ndarray, status: np.ndarray, view_centre: np.ndarray,
                     view_span: float) -> None:
        """The whole circuit in the bottom-right corner: the cars as dots and the window."""
        inset, centre, span, side = self._inset_map()
        corner = np.array([self.size - side - 4, self.size - side - 4], dtype=float)
        image.paste(inset, tuple(int(c) for c in corner))
        draw = ImageDraw.Draw(image)
        scale = side / span

        def to_inset(xy: np.ndarray) -> np.ndarray:
            return corner + np.stack([(xy[..., 0] - centre[0]) * scale + 0.5 * side,
                                      0.5 * side - (xy[..., 1] - centre[1]) * scale], axis=-1)

        half = 0.5 * view_span
        box = to_inset(np.array([view_centre - half, view_centre + half]))
        lo, hi = np.minimum(box[0], box[1]), np.maximum(box[0], box[1])
        lo, hi = np.maximum(lo, corner), np.minimum(hi, corner + side - 1)
        if np.all(hi > lo):
            draw.rectangle([*lo, *hi], outline=(255, 255, 255))
        cx, cy, _ = self.track.to_cartesian(x[:, S], x[:, N_LAT])
        for i, (px, py) in enumerate(to_inset(np.stack([cx, cy], axis=-1))):
            colour = car_colour(i) if status[i] == RACING else GHOST
            draw.ellipse([px - 3, py - 3, px + 3, py + 3], fill=colour, outline=(0, 0, 0))

    # --- a window -------------------------------------------------------------------------
    def show(self, frame: np.ndarray) -> None:
        """Display a frame in a matplotlib window (render_mode='human')."""
        import matplotlib.pyplot as plt

        if self._figure is None:
            plt.ion()
            self._figure, ax = plt.subplots(figsize=(6, 6))
            ax.set_axis_off()
            self._image = ax.imshow(frame)
        else:
            self._image.set_data(frame)
        self._figure.canvas.draw_idle()
        plt.pause(0.001)

    def close(self) -> None:
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = None


VIDEO_SUFFIXES = (".gif", ".mp4")


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write frames (uint8 HxWx3) as a looping GIF.

    Every frame is mapped to one palette of at most 255 colours, taken from up to 16
    frames spread over the race (no dithering): frames of a race share their few colours,
    and one palette encodes several times faster than a palette per frame. A frame equal
    to the one before it is merged into it (its time added to that frame's)."""
    path = Path(path)
    if not len(frames):
        raise ValueError("a GIF needs at least one frame")
    images = [Image.fromarray(np.asarray(frame, dtype=np.uint8)) for frame in frames]
    sample = np.concatenate([np.asarray(images[k]) for k in np.linspace(0, len(images) - 1, min(16, len(images)),
                                                                          dtype=int)])
    palette = Image.fromarray(sample).quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    indexed = [image.quantize(palette=palette, dither=Image.Dither.NONE) for image in images]
    path.parent.mkdir(parents=True, exist_ok=True)
    indexed[0].save(path, format="GIF", save_all=True, append_images=indexed[1:], duration=1000.0 / fps, loop=0)
    return path


def save_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write frames (uint8 HxWx3) as a GIF or an MP4 (H.264, by the suffix of ``path``).

    MP4 needs the ``video`` extra (``imageio-ffmpeg``, which ships its own ffmpeg)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"a video is written as one of {list(VIDEO_SUFFIXES)}, got {path.name!r}")
    if suffix == ".gif":
        return save_gif(frames, path, fps)
    try:
        import imageio_ffmpeg  # noqa: F401 - the writer imageio uses for MP4
    except ImportError as err:
        raise ValueError("writing MP4 needs imageio-ffmpeg: pip install 'racing-games[video]' (or write a .gif)") from err
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    # frames padded to a multiple of 16 px by the writer (H.264 blocks); yuv420p plays everywhere
    with warnings.catch_warnings():
        # imageio starts ffmpeg with fork + exec, which JAX's at-fork warning does not concern
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        with imageio.get_writer(path, fps=fps, codec="libx264", quality=7, pixelformat="yuv420p",
                                macro_block_size=16) as writer:
            for frame in frames:
                writer.append_data(np.asarray(frame, dtype=np.uint8))
    return path


def plot_race(
    track: Track,
    xs: np.ndarray,
    labels: Sequence[str] | None = None,
    title: str = "",
    path: str | Path | None = None,
):
    """Trajectories of a race: ``xs (T, N, 6)``. Left: top-down x-y; right: s-n plane.

    Returns the matplotlib figure (saved to ``path`` when given).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    xs = np.asarray(xs, dtype=float)
    num = xs.shape[1]
    labels = list(labels) if labels is not None else [f"car_{i}" for i in range(num)]
    fig, (ax_xy, ax_sn) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1, 1.4]})
    left, right = track.boundaries()
    for edge in (left, right):
        closed = np.concatenate([edge, edge[:1]]) if track.closed else edge
        ax_xy.plot(closed[:, 0], closed[:, 1], color="0.4", lw=0.8)
    for i in range(num):
        px, py, _ = track.to_cartesian(xs[:, i, S], xs[:, i, N_LAT])
        colour = np.array(car_colour(i)) / 255
        ax_xy.plot(px, py, color=colour, lw=1.5, label=labels[i])
        ax_sn.plot(xs[:, i, S], xs[:, i, N_LAT], color=colour, lw=1.5, label=labels[i])
    ax_xy.set_aspect("equal")
    ax_xy.set_xlabel("x [m]")
    ax_xy.set_ylabel("y [m]")
    s_all = xs[:, :, S].ravel()
    grid_s = np.linspace(s_all.min(), s_all.max(), 400)
    ax_sn.fill_between(grid_s, -track.width_right_at(grid_s), track.width_left_at(grid_s), color="0.9", zorder=0)
    ax_sn.set_xlabel("s [m]")
    ax_sn.set_ylabel("n [m] (left +)")
    ax_sn.legend(loc="upper right")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    return fig
