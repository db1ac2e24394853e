"""Geodetic flight logs: origin, DEM settings, lat/lon inputs and outputs, their errors."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdtm_graph.dem import import_dem
from cdtm_graph.errors import DtmError
from cdtm_graph.flightlog import DtmConfig, FlightLog, States, read_flightlog, write_flightlog
from cdtm_graph.flightlog.writer import _FlightYamlDumper
from cdtm_graph.geodesy import (
    GeodeticOrigin,
    LocalFrame,
    VerticalDatum,
    normal_gravity_mps2,
)
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from cdtm_graph.outputs import (
    GEODETIC_COLUMNS,
    TRAJECTORY_GEODETIC_CSV,
    TRAJECTORY_GEOJSON,
    write_run,
)
from cdtm_graph.results import pose_covariance_in_world
from cdtm_graph.run.prepare import dem_region_m, load_log_and_dtm

ORIGIN = GeodeticOrigin(36.5, 127.25, 120.0)
#: Geodetic -> world -> geodetic closes to this (m, and deg x 1e-5 ~ 1 m: far looser).
POSITION_TOL_M = 1e-6
ANGLE_TOL_RAD = 1e-12


def _tile(path: Path) -> Path:
    """A flat EPSG:4326 DEM (200 m above the geoid) 0.1 deg around the origin."""
    import rasterio
    from affine import Affine

    pixel = 3.0 / 3600.0
    n = int(0.2 / pixel)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs="EPSG:4326",
                       transform=Affine(pixel, 0.0, 127.15, 0.0, -pixel, 36.6)) as dst:
        dst.write(np.full((n, n), 200.0, dtype=np.float32), 1)
    return path


def _geodetic_log(base: FlightLog) -> FlightLog:
    """The small log placed near :data:`ORIGIN` over a (UTM) DEM."""
    root = base.root
    cfg = base.config
    # Positions within a few km of the origin (the synthetic log's are around zero).
    init = dataclasses.replace(cfg.initial_state, position_m=np.array([1500.0, -800.0, 900.0]))
    config = dataclasses.replace(
        cfg, origin=ORIGIN, initial_state=init,
        dtm=DtmConfig(root / "dem.tif", 4.0, vertical_datum=VerticalDatum.EGM96,
                      margin_m=2000.0, spacing_m=60.0))
    nav = dataclasses.replace(base.nav, position_m=base.nav.position_m * 100 + [0, 0, 900])
    return dataclasses.replace(base, config=config, nav=nav)


@pytest.fixture
def geolog(flightlog_files, tmp_path: Path, rng: np.random.Generator) -> FlightLog:
    log = _geodetic_log(flightlog_files.make_log(tmp_path / "log", rng))
    write_flightlog(log, log.root)
    _tile(log.root / "dem.tif")
    return log


def _edit_yaml(root: Path, edit) -> None:
    path = root / "flight.yaml"
    document = yaml.safe_load(path.read_text())
    edit(document)
    # Block mappings, lists on one line, as the writer does: errors name the key's line.
    path.write_text(yaml.dump(document, Dumper=_FlightYamlDumper, sort_keys=False,
                              default_flow_style=False))


# --------------------------------------------------------------------------- flight.yaml


def test_geodetic_log_round_trips(geolog: FlightLog):
    back = read_flightlog(geolog.root)
    assert back.config.origin == ORIGIN
    assert back.config.dtm.vertical_datum is VerticalDatum.EGM96
    assert back.config.dtm.margin_m == 2000.0
    assert back.config.dtm.spacing_m == 60.0
    assert back.config.dtm.paths == (geolog.root / "dem.tif",)
    assert back.config.initial_state == geolog.config.initial_state
    assert back.nav == geolog.nav


def test_gravity_defaults_to_wgs84_at_the_origin(geolog: FlightLog):
    _edit_yaml(geolog.root, lambda d: d.pop("gravity_mps2"))
    assert read_flightlog(geolog.root).config.gravity_mps2 == pytest.approx(
        float(normal_gravity_mps2(ORIGIN.latitude_deg, ORIGIN.height_m)), abs=1e-12)


def test_initial_state_in_latitude_longitude_and_local_enu(geolog: FlightLog):
    frame = LocalFrame(ORIGIN)
    lat, lon, h = 36.5, 127.25 + 0.25, 1500.0  # 22 km east: the verticals differ by 0.2 deg
    heading = math.radians(30.0)
    enu_R_body = np.array([[math.cos(heading), -math.sin(heading), 0.0],
                           [math.sin(heading), math.cos(heading), 0.0], [0.0, 0.0, 1.0]])

    def edit(d):
        state = d["initial_state"]
        state.pop("position_m")
        state.update(latitude_deg=lat, longitude_deg=lon, height_m=h,
                     quaternion_wxyz=rotation_to_quat_wxyz(enu_R_body).tolist(),
                     velocity_mps=[0.0, 0.0, 0.0 + 5.0])
    _edit_yaml(geolog.root, edit)
    init = read_flightlog(geolog.root).config.initial_state
    np.testing.assert_allclose(init.position_m, frame.geodetic_to_world(lat, lon, h)[0],
                               rtol=0, atol=POSITION_TOL_M)
    # Level in the local ENU there: the body's z axis is the local up, not the world's.
    up_there = frame.world_R_enu(lat, lon)[0][:, 2]
    body_z = quat_wxyz_to_rotation(init.quaternion_wxyz)[:, 2]
    assert np.linalg.norm(np.cross(body_z, up_there)) < 1e-12
    assert math.degrees(math.acos(body_z[2])) == pytest.approx(0.2, abs=0.02)
    np.testing.assert_allclose(init.velocity_mps, 5.0 * up_there, atol=1e-12)


@pytest.mark.parametrize("edit, key, words", [
    (lambda d: d["dtm"].pop("vertical_datum"), "dtm:", ("dtm.vertical_datum", "egm96")),
    (lambda d: d["dtm"].update(vertical_datum="msl"), "  vertical_datum", ("'msl'",)),
    (lambda d: d["dtm"].update(origin_enu_m=[0, 0, 0]), "  origin_enu_m", ("origin_enu_m",)),
    (lambda d: d["dtm"].update(crs="EPSG:99999999"), "  crs", ("dtm.crs",)),
    (lambda d: d["origin"].update(latitude_deg=95.0), "  latitude_deg", ("-90 to 90",)),
    (lambda d: d["initial_state"].update(latitude_deg=36.5), "  position_m",
     ("both position_m",)),
])
def test_geodetic_settings_errors_name_the_line(
    flightlog_files, geolog: FlightLog, edit, key, words
):
    _edit_yaml(geolog.root, edit)
    text = (geolog.root / "flight.yaml").read_text().split("\n")
    line = next(i for i, t in enumerate(text, 1) if t.startswith(key))
    flightlog_files.expect_error(geolog.root, "flight.yaml", line, *words)


@pytest.mark.parametrize("edit, key, words", [
    (lambda d: d["dtm"].update(vertical_datum="egm96"), "  vertical_datum", ("origin",)),
    (lambda d: d["dtm"].update(path=["dtm.npz", "dtm.npz"]), "  path", ("list of tiles",)),
    (lambda d: d["initial_state"].update(latitude_deg=36.5), "  latitude_deg",
     ("initial_state.latitude_deg without a geodetic origin",)),
    (lambda d: d.pop("gravity_mps2"), "format", ("gravity_mps2", "origin")),
])
def test_geodetic_keys_need_an_origin(flightlog_files, tmp_path: Path, rng, edit, key, words):
    log = flightlog_files.make_log(tmp_path / "log", rng)
    write_flightlog(log, log.root)
    np.savez(log.root / "dtm.npz", elevation=np.zeros((3, 3)), x0=0.0, y0=0.0, dx=30.0,
             dy=30.0)
    _edit_yaml(log.root, edit)
    text = (log.root / "flight.yaml").read_text().split("\n")
    line = next(i for i, t in enumerate(text, 1) if t.startswith(key))
    flightlog_files.expect_error(log.root, "flight.yaml", line, *words)


# --------------------------------------------------------------------------- nav / groundtruth


def _write_geodetic_states(path: Path, states: States, frame: LocalFrame) -> None:
    lat, lon, h, q, v = frame.states_to_geodetic(states.position_m,
                                                 quat_wxyz_to_rotation(states.quaternion_wxyz),
                                                 states.velocity_mps)
    rows = np.column_stack([lat, lon, h, q, v])
    lines = ["#t_ns,latitude_deg,longitude_deg,height_m,qw,qx,qy,qz,ve,vn,vu"]
    lines += [",".join([str(int(t)), *map(repr, row.tolist())])
              for t, row in zip(states.t_ns, rows)]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("name", ["nav.csv", "groundtruth.csv"])
def test_geodetic_states_are_read_into_the_world_frame(geolog: FlightLog, name):
    states = geolog.nav if name == "nav.csv" else geolog.groundtruth
    _write_geodetic_states(geolog.root / name, states, LocalFrame(ORIGIN))
    back = read_flightlog(geolog.root)
    got = back.nav if name == "nav.csv" else back.groundtruth
    np.testing.assert_array_equal(got.t_ns, states.t_ns)
    np.testing.assert_allclose(got.position_m, states.position_m, rtol=0, atol=POSITION_TOL_M)
    np.testing.assert_allclose(got.velocity_mps, states.velocity_mps, rtol=0, atol=1e-9)
    dots = np.abs(np.sum(got.quaternion_wxyz * states.quaternion_wxyz, axis=1))
    np.testing.assert_allclose(dots, 1.0, rtol=0, atol=1e-12)


def test_geodetic_states_need_an_origin(flightlog_files, tmp_path: Path, rng):
    log = flightlog_files.make_log(tmp_path / "log", rng)
    write_flightlog(log, log.root)
    np.savez(log.root / "dtm.npz", elevation=np.zeros((3, 3)), x0=0.0, y0=0.0, dx=30.0,
             dy=30.0)
    _write_geodetic_states(log.root / "nav.csv", log.nav, LocalFrame(ORIGIN))
    flightlog_files.expect_error(log.root, "nav.csv", 1, "geodetic columns", "origin")


def test_latitude_out_of_range_names_its_line(flightlog_files, geolog: FlightLog):
    _write_geodetic_states(geolog.root / "nav.csv", geolog.nav, LocalFrame(ORIGIN))
    lines = (geolog.root / "nav.csv").read_text().split("\n")
    fields = lines[2].split(",")
    fields[1] = "91.5"
    lines[2] = ",".join(fields)
    (geolog.root / "nav.csv").write_text("\n".join(lines))
    flightlog_files.expect_error(geolog.root, "nav.csv", 3, "latitude_deg is 91.5", "-90 to 90")


# --------------------------------------------------------------------------- DEM under the flight


def test_the_dem_is_read_around_the_prior_track(geolog: FlightLog):
    flight, dtm = load_log_and_dtm(geolog.root)
    xmin, xmax, ymin, ymax = dem_region_m(flight)
    track = np.vstack([flight.config.initial_state.position_m[None], flight.nav.position_m])
    assert xmin == pytest.approx(track[:, 0].min() - 2000.0)
    assert ymax == pytest.approx(track[:, 1].max() + 2000.0)
    dx0, dx1, dy0, dy1 = dtm.bounds
    assert dx0 <= xmin and dx1 >= xmax and dy0 <= ymin and dy1 >= ymax
    frame = LocalFrame(ORIGIN)
    expected = import_dem([geolog.root / "dem.tif"], frame, (xmin, xmax, ymin, ymax),
                          VerticalDatum.EGM96, spacing_m=60.0)
    assert dtm.dx == 60.0
    np.testing.assert_array_equal(dtm.elevation, expected.elevation)
    assert dtm.sigma_h() == pytest.approx(4.0, abs=1e-6)  # + resampling of a flat DEM
    assert flight.config.dtm.sigma_h_m == dtm.sigma_h()


def test_a_projected_dtm_far_from_the_flight_is_refused(flightlog_files, tmp_path: Path, rng):
    log = flightlog_files.make_log(
        tmp_path / "log", rng
    )  # dtm.origin_enu_m given, but the map is elsewhere
    log = dataclasses.replace(log, config=dataclasses.replace(
        log.config, dtm=DtmConfig(log.root / "dtm.npz", 2.4, (0.0, 0.0, 0.0))))
    write_flightlog(log, log.root)
    np.savez(log.root / "dtm.npz", elevation=np.zeros((3, 3)), x0=500000.0, y0=4100000.0,
             dx=30.0, dy=30.0)
    with pytest.raises(DtmError, match="never comes near it"):
        load_log_and_dtm(log.root)


# --------------------------------------------------------------------------- outputs


def test_geodetic_outputs_agree_with_the_world_trajectory(synthetic, tmp_path: Path, rng):
    frame = LocalFrame(ORIGIN)
    result = synthetic.synthetic_result(rng)
    write_run(tmp_path / "run", result, {}, frame=frame)
    est = result.estimate
    header = (tmp_path / "run" / TRAJECTORY_GEODETIC_CSV).read_text().split("\n")[0]
    assert header == ",".join(GEODETIC_COLUMNS)
    table = np.loadtxt(tmp_path / "run" / TRAJECTORY_GEODETIC_CSV, delimiter=",", skiprows=1)
    t_ns = np.loadtxt(tmp_path / "run" / TRAJECTORY_GEODETIC_CSV, delimiter=",", skiprows=1,
                      usecols=0, dtype=np.int64)
    np.testing.assert_array_equal(t_ns, est.t_ns)
    # Back to the world: the file holds the trajectory (read by the geodetic reader path).
    p, q, v = frame.states_from_geodetic(table[:, 1], table[:, 2], table[:, 3], table[:, 4:8],
                                         table[:, 8:11])
    np.testing.assert_allclose(p, est.position_m, rtol=0, atol=POSITION_TOL_M)
    np.testing.assert_allclose(v, est.velocity_mps, rtol=0, atol=1e-9)
    rel = np.swapaxes(quat_wxyz_to_rotation(q), 1, 2) @ est.world_T_body[:, :3, :3]
    np.testing.assert_allclose(rel, np.broadcast_to(np.eye(3), rel.shape), atol=1e-12)
    # 1-sigma north, east, up: the world position covariance turned into the local ENU.
    _, cov = pose_covariance_in_world(est.world_T_body, result.covariances.pose)
    enu_R_world = np.swapaxes(frame.world_R_enu(table[:, 1], table[:, 2]), 1, 2)
    local = enu_R_world @ cov @ np.swapaxes(enu_R_world, 1, 2)
    np.testing.assert_allclose(table[:, 11], np.sqrt(local[:, 1, 1]), rtol=1e-12)
    np.testing.assert_allclose(table[:, 12], np.sqrt(local[:, 0, 0]), rtol=1e-12)
    np.testing.assert_allclose(table[:, 13], np.sqrt(local[:, 2, 2]), rtol=1e-12)
    # GeoJSON: [longitude, latitude, height], one line and a point per frame.
    geojson = json.loads((tmp_path / "run" / TRAJECTORY_GEOJSON).read_text())
    line = geojson["features"][0]["geometry"]
    assert line["type"] == "LineString"
    np.testing.assert_allclose(np.array(line["coordinates"]), table[:, [2, 1, 3]], atol=1e-3)
    points = geojson["features"][1:]
    assert [f["properties"]["t_ns"] for f in points] == est.t_ns.tolist()
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert "latitude 36.5" in report["conventions"]["world"]


def test_trajectory_geodetic_csv_reads_back_as_groundtruth(
    synthetic, geolog: FlightLog, tmp_path, rng
):
    frame = LocalFrame(ORIGIN)
    result = synthetic.synthetic_result(rng, k=len(geolog.frames))
    result = dataclasses.replace(result, estimate=dataclasses.replace(
        result.estimate, t_ns=geolog.frames.t_ns))
    write_run(tmp_path / "run", result, {}, frame=frame)
    (geolog.root / "groundtruth.csv").write_text(
        (tmp_path / "run" / TRAJECTORY_GEODETIC_CSV).read_text())
    gt = read_flightlog(geolog.root).groundtruth
    np.testing.assert_allclose(gt.position_m, result.estimate.position_m, rtol=0,
                               atol=POSITION_TOL_M)


def test_no_geodetic_outputs_without_a_frame(synthetic, tmp_path: Path, rng):
    write_run(tmp_path / "run", synthetic.synthetic_result(rng), {})
    assert not (tmp_path / "run" / TRAJECTORY_GEODETIC_CSV).exists()
    assert not (tmp_path / "run" / TRAJECTORY_GEOJSON).exists()


# --------------------------------------------------------------------------- end to end


def test_the_worked_example_end_to_end(tmp_path: Path):
    """docs/geodesy.md's example: a lat/lon flight over an EPSG:4326 EGM96 tile."""
    import rasterio

    from cdtm_graph.cli import main

    log, run = tmp_path / "my_flight", tmp_path / "my_run"
    assert main(["simulate", str(log), "--origin", "36.5", "127.25", "120", "--frames", "8",
                 "--nav", "noisy_truth"]) == 0
    document = yaml.safe_load((log / "flight.yaml").read_text())
    assert document["dtm"] == {"path": "dem.tif", "sigma_h_m": 2.4, "vertical_datum": "egm96",
                               "horizontal_offset_sigma_m": 0.0, "vertical_offset_sigma_m": 0.0}
    assert "latitude_deg" in document["initial_state"]
    assert (log / "groundtruth.csv").read_text().startswith(
        "#t_ns,latitude_deg,longitude_deg,height_m,")
    with rasterio.open(log / "dem.tif") as src:
        assert src.crs.to_epsg() == 4326
    assert main(["smooth", str(log), "--out", str(run), "--plots", "--quiet"]) == 0
    assert {"trajectory_geodetic.csv", "trajectory.geojson", "trajectory_dem.png"} <= {
        p.name for p in run.iterdir()}
    # The geodetic trajectory against the (geodetic) ground truth, in metres on the ground.
    flight = read_flightlog(log)
    frame = flight.config.local_frame
    table = np.loadtxt(run / "trajectory_geodetic.csv", delimiter=",", skiprows=1)
    estimate = frame.geodetic_to_world(table[:, 1], table[:, 2], table[:, 3])
    truth = flight.groundtruth.interpolate(flight.frames.t_ns).position_m
    error = np.linalg.norm(estimate - truth, axis=1)
    sigma = np.linalg.norm(table[:, 11:14], axis=1)
    assert np.all(error < 4 * sigma)
    assert error.max() < 5.0  # a 30 m DEM, 1000 m above ground: metres, not tens


def test_the_dem_plot_draws_in_the_dems_own_coordinates(synthetic, tmp_path: Path, rng):
    from cdtm_graph.dem import read_dem_window
    from cdtm_graph.plots.dem import plot_trajectory_over_dem
    from cdtm_graph.results import TrajectoryEstimate
    from cdtm_graph.sim.geodetic import write_dem_tile

    frame = LocalFrame(ORIGIN)
    native = synthetic.smooth_native_dtm()
    k = 12
    position = np.column_stack([np.linspace(26500, 29500, k), np.linspace(16500, 18500, k),
                                np.full(k, 1500.0)])
    T = np.tile(np.eye(4), (k, 1, 1))
    T[:, :3, 3] = position
    estimate = TrajectoryEstimate(np.arange(k, dtype=np.int64), T, np.zeros((k, 3)),
                                  np.zeros((k, 3)), np.zeros((k, 3)))
    cov = np.tile(np.diag([25.0, 4.0, 9.0]), (k, 1, 1))
    region = (26000.0, 30000.0, 16000.0, 19000.0)
    for crs, pixel in (("EPSG:4326", 1 / 3600), ("EPSG:32652", 30.0)):
        tile = write_dem_tile(native, frame, tmp_path / f"{pixel}.tif", crs, pixel)
        window = read_dem_window([tile], frame, region, VerticalDatum.ELLIPSOID)
        fig = plot_trajectory_over_dem(tmp_path / "dem.png", window, frame, estimate, cov)
        line = next(ln for ln in fig.axes[0].lines if ln.get_label() == "estimate")
        lat, lon, _ = frame.world_to_geodetic(position)
        x, y = window.to_crs(lat, lon)
        np.testing.assert_allclose(line.get_xdata(), x, rtol=1e-12)
        np.testing.assert_allclose(line.get_ydata(), y, rtol=1e-12)
        assert (tmp_path / "dem.png").stat().st_size > 0


#: An ellipse narrower than this on screen cannot be seen (issue 23: about 1 px at true size).
MIN_ELLIPSE_PX = 8.0


def test_the_dem_plots_ellipses_are_visible_and_the_truth_is_drawn_over_the_estimate(
        tmp_path: Path, synthetic):
    """trajectory_dem.png: 1 m ellipses on a 4 km track are magnified until they measure
    at least MIN_ELLIPSE_PX on screen, the factor in the legend; the ground truth's line is
    drawn above the estimate's; the IMU-only track is there.

    Catches: true-size ellipses (about 1 px: issue 23), the truth under the estimate
    (zorder 2 < 3 before), no IMU-only track."""
    from cdtm_graph.dem import read_dem_window
    from cdtm_graph.flightlog import States
    from cdtm_graph.plots.dem import plot_trajectory_over_dem
    from cdtm_graph.results import TrajectoryEstimate
    from cdtm_graph.sim.geodetic import write_dem_tile

    frame = LocalFrame(ORIGIN)
    k = 12
    position = np.column_stack([np.linspace(26500, 29500, k), np.linspace(16500, 18500, k),
                                np.full(k, 1500.0)])
    T = np.tile(np.eye(4), (k, 1, 1))
    T[:, :3, 3] = position
    zeros = np.zeros((k, 3))
    estimate = TrajectoryEstimate(np.arange(k, dtype=np.int64), T, zeros, zeros, zeros)
    free = TrajectoryEstimate(np.arange(k, dtype=np.int64), T.copy(),
                              zeros, zeros, zeros)
    free.world_T_body[:, 0, 3] += np.linspace(0.0, 300.0, k)
    truth = States(estimate.t_ns, position + [2.0, -1.0, 0.0], np.tile([1.0, 0, 0, 0], (k, 1)),
                   zeros)
    cov = np.tile(np.diag([1.0, 0.5, 1.0]), (k, 1, 1))  # 3 m at 3 sigma
    tile = write_dem_tile(synthetic.smooth_native_dtm(), frame, tmp_path / "dem.tif",
                          "EPSG:4326", 1 / 3600)
    window = read_dem_window([tile], frame, (26000.0, 30000.0, 16000.0, 19000.0),
                             VerticalDatum.ELLIPSOID)
    fig = plot_trajectory_over_dem(tmp_path / "dem.png", window, frame, estimate, cov, truth,
                                   free=free)
    ax = fig.axes[0]
    lines = {ln.get_label(): ln for ln in ax.lines}
    assert lines["ground truth"].get_zorder() > lines["estimate"].get_zorder()
    assert any(label.startswith("IMU only") for label in lines)
    (legend,) = [label for label in lines if label.startswith("3σ horizontal")]
    assert "magnified ×" in legend
    outlines = [ln for ln in ax.lines if ln.get_label().startswith("_") and
                ln.get_color() == "tab:blue"]
    assert len(outlines) == k
    for outline in outlines:
        px = ax.transData.transform(outline.get_xydata())
        assert np.ptp(px, axis=0).min() >= MIN_ELLIPSE_PX
