"""Tests of racing_env.track: geometry, JAX lookups, builders and input validation."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from racing_env import track as tr

CSV_FILES = sorted(tr.circuits_dir().glob("*.csv"))  # the shipped circuits


@pytest.fixture(scope="module")
def trefoil() -> tr.Track:
    return tr.trefoil()


def _circle(radius: float, num: int, clockwise: bool = False) -> tr.Track:
    theta = np.linspace(0.0, 2.0 * np.pi, num, endpoint=False)
    if clockwise:
        theta = -theta
    width = np.full(num, 5.0)
    # Noise-free samples: smoothing 0 (the smoothing parameter is the assumed noise).
    return tr.from_centerline(
        radius * np.cos(theta), radius * np.sin(theta), width, width, smoothing=0.0
    )


def _open_arc() -> tr.Track:
    """A quarter circle (R = 100 m, left turn) as an open track with varying widths."""
    theta = np.linspace(-0.5 * np.pi, 0.0, 60)
    w = np.linspace(4.0, 8.0, 60)
    return tr.from_centerline(
        100.0 * np.cos(theta), 100.0 + 100.0 * np.sin(theta), w, w + 1.0,
        closed=False, smoothing=0.0, name="arc",
    )


# ------------------------------------------------------------------------------------------
# Geometry.


@pytest.mark.parametrize("clockwise", [False, True])
def test_circle_curvature(clockwise: bool) -> None:
    # A cubic interpolating spline through points h = 1.57 m apart on R = 50 m reproduces
    # the curvature to O((h/R)^2) ~ 1e-3; 1% leaves margin.
    radius = 50.0
    track = _circle(radius, 200, clockwise)
    sign = -1.0 if clockwise else 1.0
    np.testing.assert_allclose(sign * track.kappa, 1.0 / radius, rtol=0.01)
    assert track.closed
    assert track.length == pytest.approx(2.0 * np.pi * radius, rel=1e-4)
    # Uniform grid with no duplicated end point, and the heading turns once around.
    np.testing.assert_allclose(track.s, np.arange(track.num_points) * track.ds)
    assert track.s[-1] == pytest.approx(track.length - track.ds)
    turn = track.heading[-1] - track.heading[0] + track.ds * track.kappa[-1]
    assert turn == pytest.approx(sign * 2.0 * np.pi, rel=1e-3)


@pytest.mark.parametrize("name", ["trefoil", "straight", "arc", "random"])
def test_frenet_cartesian_round_trip(name: str, trefoil: tr.Track) -> None:
    # to_cartesian blends offset grid points linearly and from_cartesian inverts that exact
    # map (a quadratic per segment), so the round trip is exact up to rounding for
    # |n| < 1/|kappa| (here |n| <= 6 m, radii >= 75 m): 1e-9 m is ~1e3 x rounding error.
    track = {
        "trefoil": trefoil,
        "straight": tr.straight(),
        "arc": _open_arc(),
        "random": tr.random_circuit(3),
    }[name]
    rng = np.random.default_rng(0)
    w = min(track.width_left.min(), track.width_right.min())
    s = rng.uniform(0.0, track.length, 500)
    n = rng.uniform(-w, w, 500)
    x, y, _ = track.to_cartesian(s, n)
    s2, n2 = track.from_cartesian(x, y)
    np.testing.assert_allclose(np.asarray(track.wrap_ds(s2 - s)), 0.0, atol=1e-9)
    np.testing.assert_allclose(n2, n, atol=1e-9)


def test_to_cartesian_conventions(trefoil: tr.Track) -> None:
    # On the grid, to_cartesian returns the stored centreline; n > 0 lies to the left.
    k = np.arange(0, trefoil.num_points, 7)
    x, y, h = trefoil.to_cartesian(trefoil.s[k], 0.0)
    np.testing.assert_allclose(x, trefoil.x[k], atol=1e-9)
    np.testing.assert_allclose(y, trefoil.y[k], atol=1e-9)
    np.testing.assert_allclose(h, trefoil.heading[k], atol=1e-12)
    xl, yl, _ = trefoil.to_cartesian(trefoil.s[k], 1.0)
    left = np.cos(h) * (yl - y) - np.sin(h) * (xl - x)  # cross(tangent, offset)
    np.testing.assert_allclose(left, 1.0, atol=1e-9)
    # Broadcasting and the boundaries lie at n = width_left and n = -width_right.
    assert trefoil.to_cartesian(np.zeros((3, 1)), np.zeros(4))[0].shape == (3, 4)
    left_xy, right_xy = trefoil.boundaries()
    assert left_xy.shape == right_xy.shape == (trefoil.num_points, 2)
    s_l, n_l = trefoil.from_cartesian(left_xy[:, 0], left_xy[:, 1])
    _, n_r = trefoil.from_cartesian(right_xy[:, 0], right_xy[:, 1])
    np.testing.assert_allclose(n_l, trefoil.width_left, atol=1e-9)
    np.testing.assert_allclose(n_r, -trefoil.width_right, atol=1e-9)
    np.testing.assert_allclose(np.asarray(trefoil.wrap_ds(s_l - trefoil.s)), 0.0, atol=1e-9)


def test_straight_geometry() -> None:
    track = tr.straight(length=100.0, width_left=3.0, width_right=4.0)
    assert not track.closed and track.num_points == 101 and track.ds == pytest.approx(1.0)
    assert track.s[-1] == pytest.approx(track.length)
    x, y, h = track.to_cartesian(np.array([10.0, 120.0]), np.array([2.0, -1.0]))
    np.testing.assert_allclose(x, [10.0, 100.0])  # s clamps at the end
    np.testing.assert_allclose(y, [2.0, -1.0])
    np.testing.assert_allclose(h, 0.0)
    # Beyond the ends: s clamps, n is the offset from the extended centreline.
    s, n = track.from_cartesian(np.array([110.0, -5.0]), np.array([2.0, -3.0]))
    np.testing.assert_allclose(s, [100.0, 0.0])
    np.testing.assert_allclose(n, [2.0, -3.0])


@pytest.mark.parametrize("path", CSV_FILES, ids=lambda p: p.stem)
def test_from_csv_real_tracks(path: Path) -> None:
    track = tr.from_csv(path)
    data = np.loadtxt(path, delimiter=",", comments="#")
    closed_xy = np.vstack([data[:, :2], data[:1, :2]])
    polyline_length = np.sum(np.hypot(*np.diff(closed_xy, axis=0).T))
    assert track.closed and track.name == path.stem
    assert track.length == pytest.approx(polyline_length, rel=0.02)
    assert np.all(np.isfinite(track.kappa))
    assert np.all(track.width_left > 0) and np.all(track.width_right > 0)
    # The widths are carried over from the file.
    assert track.width_left.min() >= data[:, 3].min() - 1e-9
    assert track.width_left.max() <= data[:, 3].max() + 1e-9
    # The smoothed centreline stays within the track (well within the narrowest half-width).
    _, n = track.from_cartesian(data[:, 0], data[:, 1])
    assert np.abs(n).max() < 0.5 * data[:, 2:].min()


def test_trefoil_turns_both_ways(trefoil: tr.Track) -> None:
    # Predicted extrema of r = R(1 + a sin 3t): (1 + 10a)/(R(1+a)^2), (1 - 10a)/(R(1-a)^2).
    a, radius = 0.25, 200.0
    assert trefoil.kappa.max() > 0 and trefoil.kappa.min() < 0
    assert trefoil.kappa.min() == pytest.approx((1 - 10 * a) / (radius * (1 - a) ** 2), rel=0.01)
    # Positive total turning: driven counter-clockwise.
    assert np.sum(trefoil.kappa) * trefoil.ds == pytest.approx(2.0 * np.pi, rel=1e-3)
    np.testing.assert_allclose(trefoil.width_left, 6.0)
    np.testing.assert_allclose(trefoil.width_right, 6.0)


def test_random_circuit_deterministic() -> None:
    a, b, c = tr.random_circuit(7), tr.random_circuit(7), tr.random_circuit(8)
    for field in ("x", "y", "kappa", "s"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.length == b.length and a.length != c.length
    radius = np.hypot(a.x, a.y)
    assert radius.min() > 0.5 * 200.0
    assert np.sum(a.kappa) * a.ds == pytest.approx(2.0 * np.pi, rel=1e-3)


# ------------------------------------------------------------------------------------------
# JAX lookups.


def test_lookups_periodic_on_closed(trefoil: tr.Track) -> None:
    s = jnp.linspace(-50.0, 50.0, 37)
    for fn in (trefoil.kappa_at, trefoil.width_left_at, trefoil.width_right_at):
        np.testing.assert_allclose(fn(s), fn(s + trefoil.length), atol=1e-12)
        np.testing.assert_allclose(fn(s), fn(s - 3.0 * trefoil.length), atol=1e-10)
    # Grid points are reproduced; midpoints are averages (linear interpolation).
    np.testing.assert_allclose(trefoil.kappa_at(trefoil.s), trefoil.kappa, atol=1e-15)
    mid = trefoil.s[:-1] + 0.5 * trefoil.ds
    np.testing.assert_allclose(
        trefoil.kappa_at(mid), 0.5 * (trefoil.kappa[:-1] + trefoil.kappa[1:]), atol=1e-15
    )
    # The closing segment interpolates between the last and the first grid point.
    last = trefoil.kappa_at(trefoil.length - 0.5 * trefoil.ds)
    assert last == pytest.approx(0.5 * (trefoil.kappa[-1] + trefoil.kappa[0]))
    assert trefoil.kappa_at(jnp.zeros((2, 3))).shape == (2, 3)
    assert trefoil.kappa_at(5).shape == ()


def test_lookups_clamped_on_open() -> None:
    arc = _open_arc()
    assert arc.width_left_at(-10.0) == pytest.approx(arc.width_left[0])
    assert arc.width_left_at(arc.length + 10.0) == pytest.approx(arc.width_left[-1])
    assert arc.width_right_at(arc.length) == pytest.approx(arc.width_right[-1])
    np.testing.assert_allclose(arc.kappa, 0.01, rtol=0.01)
    np.testing.assert_allclose(arc.wrap_s(jnp.array([-1.0, 5.0, 1e4])), [0.0, 5.0, arc.length])
    np.testing.assert_allclose(arc.wrap_ds(jnp.array([-1e4, 3.0])), [-1e4, 3.0])


def test_wrap_ds_range(trefoil: tr.Track) -> None:
    length = trefoil.length
    d = jnp.concatenate(
        [jnp.linspace(-3 * length, 3 * length, 1001), jnp.array([0.5 * length, -0.5 * length])]
    )
    w = np.asarray(trefoil.wrap_ds(d))
    assert np.all(w >= -0.5 * length) and np.all(w < 0.5 * length)
    np.testing.assert_allclose(np.mod(w - np.asarray(d) + 0.5, length) - 0.5, 0.0, atol=1e-9)
    s = np.asarray(trefoil.wrap_s(d))
    assert np.all(s >= 0.0) and np.all(s < length)


def test_jit_vmap_grad(trefoil: tr.Track) -> None:
    s = jnp.linspace(0.0, 2.0 * trefoil.length, 11)
    expected = trefoil.kappa_at(s)

    # The Track as a jit argument (arrays are traced leaves, meta data is static).
    @jax.jit
    def lookup(track: tr.Track, s: jax.Array) -> jax.Array:
        return track.kappa_at(s) + track.width_left_at(s) - track.width_right_at(s)

    np.testing.assert_allclose(lookup(trefoil, s), expected, atol=1e-15)
    np.testing.assert_allclose(jax.vmap(trefoil.kappa_at)(s), expected, atol=1e-15)
    assert len(jax.tree_util.tree_leaves(trefoil)) == 7

    grad = jax.vmap(jax.grad(trefoil.kappa_at))(s + 0.3)
    assert np.all(np.isfinite(grad))
    # Inside a cell the derivative is the slope of the interpolant.
    k = int((0.3 + s[1]) // trefoil.ds) % trefoil.num_points
    slope = (trefoil.kappa[k + 1] - trefoil.kappa[k]) / trefoil.ds
    assert grad[1] == pytest.approx(slope)
    assert np.isfinite(jax.jit(jax.grad(tr.straight().kappa_at))(10.0))


# ------------------------------------------------------------------------------------------
# Builders and validation.


def _write(tmp_path: Path, rows: list[str], name: str = "bad.csv") -> Path:
    path = tmp_path / name
    path.write_text("# x_m,y_m,w_tr_right_m,w_tr_left_m\n" + "\n".join(rows) + "\n")
    return path


def _circle_rows(num: int = 40) -> list[str]:
    theta = np.linspace(0.0, 2.0 * np.pi, num, endpoint=False)
    return [f"{100 * np.cos(t):.6f},{100 * np.sin(t):.6f},5.0,5.5" for t in theta]


def test_from_csv_good_file(tmp_path: Path) -> None:
    track = tr.from_csv(_write(tmp_path, _circle_rows(), "ring.csv"), ds=2.0)
    assert track.name == "ring" and track.closed
    assert track.ds == pytest.approx(2.0, rel=0.01)
    np.testing.assert_allclose(track.width_right, 5.0)
    np.testing.assert_allclose(track.width_left, 5.5)
    assert tr.get_track(str(tmp_path / "ring.csv")).length == pytest.approx(
        tr.from_csv(tmp_path / "ring.csv").length
    )


@pytest.mark.parametrize(
    "bad_row, match",
    [
        ("1.0,2.0,3.0", r"bad\.csv:4: expected 4 columns"),
        ("1.0,2.0,3.0,4.0,5.0", r"bad\.csv:4: expected 4 columns"),
        ("1.0,abc,3.0,4.0", r"bad\.csv:4: non-numeric"),
        ("1.0,2.0,-3.0,4.0", r"bad\.csv:4: track widths must be > 0"),
        ("1.0,2.0,3.0,0.0", r"bad\.csv:4: track widths must be > 0"),
        ("1.0,nan,3.0,4.0", r"bad\.csv:4: non-finite"),
    ],
)
def test_from_csv_malformed(tmp_path: Path, bad_row: str, match: str) -> None:
    rows = _circle_rows()
    rows[2] = bad_row  # file line 4 (after the header)
    with pytest.raises(ValueError, match=match):
        tr.from_csv(_write(tmp_path, rows))


def test_from_csv_too_short_and_missing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"short\.csv: need at least 10 centreline points"):
        tr.from_csv(_write(tmp_path, _circle_rows()[:5], "short.csv"))
    with pytest.raises(FileNotFoundError, match=r"track file not found: .*nope\.csv"):
        tr.from_csv(tmp_path / "nope.csv")


def test_from_centerline_validation() -> None:
    theta = np.linspace(0.0, 2.0 * np.pi, 30, endpoint=False)
    x, y, w = 50 * np.cos(theta), 50 * np.sin(theta), np.full(30, 4.0)
    with pytest.raises(ValueError, match="equal lengths"):
        tr.from_centerline(x, y[:-1], w, w)
    with pytest.raises(ValueError, match=r"width_left must be > 0"):
        tr.from_centerline(x, y, w, -w)
    with pytest.raises(ValueError, match="x must be finite"):
        tr.from_centerline(np.where(theta > 1, np.inf, x), y, w, w)
    with pytest.raises(ValueError, match="at least 10 distinct"):
        tr.from_centerline(x[:9], y[:9], w[:9], w[:9])
    with pytest.raises(ValueError, match="smoothing must be >= 0"):
        tr.from_centerline(x, y, w, w, smoothing=-1.0)
    # A repeated closing point and consecutive duplicates are dropped, not fitted.
    base = tr.from_centerline(x, y, w, w)
    closed = tr.from_centerline(np.append(x, x[0]), np.append(y, y[0]), np.append(w, 4.0),
                                np.append(w, 4.0))
    dup = tr.from_centerline(np.insert(x, 5, x[5]), np.insert(y, 5, y[5]), np.append(w, 4.0),
                             np.append(w, 4.0))
    assert closed.length == pytest.approx(base.length, rel=1e-12)
    assert dup.length == pytest.approx(base.length, rel=1e-12)


def test_track_validation() -> None:
    good = tr.straight(length=10.0)
    fields = {f: getattr(good, f) for f in ("s", "kappa", "width_left", "width_right", "x",
                                            "y", "heading")}
    with pytest.raises(ValueError, match="width_right must be > 0"):
        tr.Track(**{**fields, "width_right": -fields["width_right"]}, length=10.0, closed=False)
    with pytest.raises(ValueError, match="same shape"):
        tr.Track(**{**fields, "kappa": np.zeros(3)}, length=10.0, closed=False)
    with pytest.raises(ValueError, match="length must be finite and > 0"):
        tr.Track(**fields, length=-1.0, closed=False)
    with pytest.raises(ValueError, match="uniform grid"):
        tr.Track(**fields, length=10.0, closed=True)  # closed grid must omit the end point
    with pytest.raises(ValueError, match="at least 4 grid points"):
        tr.Track(**{f: a[:3] for f, a in fields.items()}, length=2.0, closed=False)
    assert not good.kappa.flags.writeable  # immutable
    assert repr(good) == "Track(name='straight', length=10.0 m, closed=False, M=11)"


def test_track_from_jax_arrays_is_validated_and_copied_like_numpy() -> None:
    """Concrete JAX arrays are checked and stored as read-only float64 NumPy copies; only
    tracers (inside jit/vmap) skip the checks."""
    good = tr.straight(length=10.0)
    fields = {f: jnp.asarray(getattr(good, f)) for f in ("s", "kappa", "width_left", "width_right", "x",
                                                         "y", "heading")}
    with pytest.raises(ValueError, match="width_left must be > 0"):
        tr.Track(**{**fields, "width_left": fields["width_left"].at[5:].set(-3.0)}, length=10.0, closed=False)
    with pytest.raises(ValueError, match="must be finite everywhere"):
        tr.Track(**{**fields, "kappa": fields["kappa"].at[0].set(jnp.nan)}, length=10.0, closed=False)
    track = tr.Track(**fields, length=10.0, closed=False)
    assert isinstance(track.kappa, np.ndarray) and track.kappa.dtype == np.float64
    assert not track.kappa.flags.writeable
    np.testing.assert_array_equal(track.width_left, good.width_left)
    # a Track returned by a jitted function is rebuilt from concrete arrays: checked, NumPy again
    out = jax.jit(lambda t: t)(good)
    assert isinstance(out.s, np.ndarray) and out.s.tobytes() == good.s.tobytes()
    # built from tracers (invalid widths included) it is not checked: its values are unknown
    widths = jax.jit(lambda w: tr.Track(**{**fields, "width_left": w}, length=10.0, closed=False).width_left_at(2.0))
    assert float(widths(-jnp.ones(11))) == -1.0


def test_get_track(trefoil: tr.Track) -> None:
    assert set(tr.BUILTIN_TRACKS) >= {"straight", "trefoil"}
    assert tr.get_track(trefoil) is trefoil
    assert tr.get_track("straight").name == "straight"
    assert tr.get_track("trefoil").length == pytest.approx(trefoil.length)
    with pytest.raises(ValueError, match=r"unknown track 'nurburgring'.*'straight'"):
        tr.get_track("nurburgring")


# --- the shipped circuits ---------------------------------------------------------------


def test_every_shipped_circuit_has_its_racing_line_and_the_license_beside_it() -> None:
    names = tr.circuit_names()
    assert len(names) == 25 and {"Monza", "Spa", "Suzuka", "Silverstone"} <= set(names)
    for name in names:
        assert tr.raceline_path(name).is_file()
    assert "LESSER GENERAL PUBLIC LICENSE" in (tr.circuits_dir() / "LICENSE").read_text()
    assert "TUMFTM" in (tr.circuits_dir() / "README.md").read_text()


@pytest.mark.parametrize("spelling", ["Monza", "monza", "MONZA"])
def test_a_circuit_by_name_in_any_case_is_the_fitted_file(spelling: str) -> None:
    track = tr.get_track(spelling)
    assert track.name == "Monza" and track.closed
    assert track is tr.get_track("Monza")  # one cached fit
    fresh = tr.from_csv(tr.circuits_dir() / "Monza.csv")
    np.testing.assert_array_equal(track.kappa, fresh.kappa)
    assert track.length == fresh.length


def test_a_cached_circuit_loads_in_under_50_ms() -> None:
    import time

    tr.get_track("Spa")
    start = time.perf_counter()
    tr.get_track("spa")
    tr.get_track("Spa")
    assert time.perf_counter() - start < 0.05


@pytest.mark.parametrize("track", [None, 3, ["trefoil"]])
def test_a_track_of_no_kind_is_refused_naming_what_a_track_may_be(track) -> None:
    import racing_env

    allowed = r"track must be a Track, a builtin track name \[.*'trefoil'.*\], a shipped circuit's name .* \.csv file"
    with pytest.raises(TypeError, match=allowed):
        tr.get_track(track)
    with pytest.raises(TypeError, match=allowed):
        racing_env.parallel_env(track=track)


def test_an_unknown_track_name_lists_the_known_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown track 'Monzza'.*'trefoil'.*'Monza'.*'Zandvoort'"):
        tr.get_track("Monzza")
    with pytest.raises(ValueError, match=r"unknown circuit 'Imola'.*'Suzuka'"):
        tr.circuit("Imola")
    with pytest.raises(ValueError, match=r"no racing line is shipped for 'trefoil'"):
        tr.raceline_path("trefoil")


def test_a_path_still_loads_a_csv_of_the_format(tmp_path: Path) -> None:
    copy = tmp_path / "MyMonza.csv"
    copy.write_text((tr.circuits_dir() / "Monza.csv").read_text())
    track = tr.get_track(str(copy))
    assert track.name == "MyMonza"
    assert track.length == pytest.approx(tr.get_track("Monza").length, rel=1e-12)


def test_track_summary_counts_the_trefoils_six_corners_and_none_on_a_straight() -> None:
    # The trefoil: three left-hand lobes and three right turns between them (lobe 0.25 > 0.1).
    summary = tr.track_summary(tr.trefoil())
    assert summary["corners"] == 6 and summary["closed"]
    assert summary["mean_width"] == pytest.approx(12.0) and summary["min_width"] == pytest.approx(12.0)
    # its tightest radius is at the right turns: R (1 - a)^2 / (10 a - 1) = 75 m for R = 200, a = 0.25
    assert summary["min_radius"] == pytest.approx(75.0, rel=1e-3)
    assert tr.track_summary(tr.straight())["corners"] == 0
    assert tr.count_corners(tr.random_circuit(0)) == 0  # radius everywhere above 100 m
