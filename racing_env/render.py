"""Drawing: top-down frames (uint8 RGB), trajectory plots and GIF export.

Frames are drawn with Pillow on a cached background of the track, so an ``rgb_array``
frame costs about a millisecond. Plots use matplotlib.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw

from racing_env.dynamics import CHI, N_LAT, S
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

CAR_COLOURS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
    (148, 103, 189), (140, 86, 75), (227, 119, 194), (127, 127, 127),
]
GRASS, ASPHALT, LINE = (96, 140, 80), (70, 70, 74), (235, 235, 235)
FOLLOW_WINDOW = 160.0  # [m] side of the square shown by the follow camera


def car_colour(index: int) -> tuple[int, int, int]:
    return CAR_COLOURS[index % len(CAR_COLOURS)]


def car_polygons(track: Track, x: np.ndarray, vehicles: VehicleParams) -> np.ndarray:
    """World corners of every car footprint, ``(N, 4, 2)`` [m]."""
    cx, cy, heading = track.to_cartesian(x[:, S], x[:, N_LAT])
    yaw = heading + x[:, CHI]
    half_l = 0.5 * np.asarray(vehicles.length)[:, None]
    half_w = 0.5 * np.asarray(vehicles.width)[:, None]
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float)
    lx, ly = local[None, :, 0] * half_l, local[None, :, 1] * half_w
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([cx[:, None] + c * lx - s * ly, cy[:, None] + s * lx + c * ly], axis=-1)


class Renderer:
    """Top-down frames of a race. ``camera``: ``track``, ``follow`` or ``auto``
    (whole track when it fits in about 600 m, else follow the cars)."""

    def __init__(self, track: Track, vehicles: VehicleParams, size: int = 512, camera: str = "auto"):
        self.track, self.vehicles, self.size = track, vehicles, int(size)
        left, right = track.boundaries()
        self._left, self._right = left, right
        pts = np.concatenate([left, right])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        extent = float(np.max(hi - lo))
        if camera == "auto":
            camera = "track" if extent <= 600.0 else "follow"
        self.camera = camera
        self._track_view = (0.5 * (lo + hi), 1.08 * extent)
        self._background = self._draw_track(*self._track_view) if camera == "track" else None
        self._figure = None

    def _to_px(self, xy: np.ndarray, centre: np.ndarray, span: float) -> np.ndarray:
        scale = self.size / span
        px = (xy[..., 0] - centre[0]) * scale + 0.5 * self.size
        py = 0.5 * self.size - (xy[..., 1] - centre[1]) * scale
        return np.stack([px, py], axis=-1)

    def _draw_track(self, centre: np.ndarray, span: float) -> Image.Image:
        image = Image.new("RGB", (self.size, self.size), GRASS)
        draw = ImageDraw.Draw(image)
        left = self._to_px(self._left, centre, span)
        right = self._to_px(self._right, centre, span)
        count = len(left) if self.track.closed else len(left) - 1
        for k in range(count):
            k1 = (k + 1) % len(left)
            quad = [tuple(left[k]), tuple(left[k1]), tuple(right[k1]), tuple(right[k])]
            draw.polygon(quad, fill=ASPHALT)
        for edge in (left, right):
            points = [tuple(p) for p in edge] + ([tuple(edge[0])] if self.track.closed else [])
            draw.line(points, fill=LINE, width=1)
        start = np.stack([left[0], right[0]])
        draw.line([tuple(p) for p in start], fill=(250, 250, 250), width=3)
        return image

    def frame(self, x: np.ndarray, active: np.ndarray | None = None, title: str = "") -> np.ndarray:
        """A frame of the joint state ``x (N, 6)`` as ``uint8 (size, size, 3)``."""
        x = np.asarray(x, dtype=float)
        if self.camera == "track":
            centre, span = self._track_view
            image = self._background.copy()
        else:
            cx, cy, _ = self.track.to_cartesian(x[:, S], x[:, N_LAT])
            centre, span = np.array([cx.mean(), cy.mean()]), FOLLOW_WINDOW
            image = self._draw_track(centre, span)
        draw = ImageDraw.Draw(image)
        corners = self._to_px(car_polygons(self.track, x, self.vehicles), centre, span)
        for i, quad in enumerate(corners):
            colour = car_colour(i) if active is None or active[i] else (200, 200, 200)
            # a car never drawn smaller than 4 px so it stays visible on big tracks
            mid = quad.mean(axis=0)
            quad = mid + (quad - mid) * max(1.0, 4.0 / max(np.ptp(quad[:, 0]), 1e-6))
            draw.polygon([tuple(p) for p in quad], fill=colour, outline=(0, 0, 0))
        if title:
            draw.text((6, 6), title, fill=(255, 255, 255))
        return np.asarray(image, dtype=np.uint8)

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


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write frames (uint8 HxWx3) as a looping GIF."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack(frames), duration=1000.0 / fps, loop=0)
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
