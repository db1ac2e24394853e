"""Accuracy map: flat terrain flagged, rough terrain mapped, each node = analyze_pair by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cdtm_graph.analysis.accuracy_map import (
    DEGENERACY_CODE_NAMES,
    AccuracyMapSettings,
    AltitudeReference,
    DegeneracyCode,
    accuracy_at,
    accuracy_map,
    map_nodes,
)
from cdtm_graph.analysis.closed_form import analyze_pair
from cdtm_graph.cli import main as cdtm_main
from cdtm_graph.dtm import Dtm, save_dtm_npz
from cdtm_graph.errors import CdtmError
from cdtm_graph.geometry import so3_log
from cdtm_graph.parallel import ParallelSettings
from cdtm_graph.sim.terrain import fractal_terrain

#: The map stores exactly what analyze_pair returns (same inputs, same arithmetic).
SAME_NUMBER_RTOL = 1e-12
#: Noiseless features: the second ray reprojects its ground point to rounding.
REPROJECTION_TOL = 1e-12
#: Terrain: 2.4 x 2.4 km at 20 m; x < 0 is flat, x >= 0 is 300 m of fractal relief.
SIZE_M, SPACING_M = 2400.0, 20.0
#: Nodes whose whole footprint (half-width ~350 m at 500 m over 60 degrees, plus the
#: 40 m baseline) stays on one side of x = 0.
FOOTPRINT_CLEARANCE_M = 450.0
SETTINGS = AccuracyMapSettings(altitude_m=500.0, fov_deg=60.0, step_m=200.0, sigma_h_m=2.4)


@pytest.fixture(scope="module")
def half_flat_dtm(seed) -> Dtm:
    rough = fractal_terrain(size_m=SIZE_M, spacing_m=SPACING_M, relief_m=300.0,
                            seed=seed, origin_xy=(-SIZE_M / 2, -SIZE_M / 2))
    x = rough.x0 + np.arange(rough.shape[1]) * rough.dx
    elevation = np.where(x[None, :] < 0.0, 0.0, rough.elevation)
    return Dtm(elevation, rough.x0, rough.y0, rough.dx, rough.dy, sigma_h_m=2.4)


@pytest.fixture(scope="module")
def amap(half_flat_dtm):
    return accuracy_map(half_flat_dtm, SETTINGS)


def test_flat_region_is_degenerate_and_rough_region_is_mapped(amap):
    flat = amap.x_m < -FOOTPRINT_CLEARANCE_M
    rough = amap.x_m > FOOTPRINT_CLEARANCE_M
    assert flat.any() and rough.any()
    assert np.all(amap.reason_codes[:, flat] & DegeneracyCode.FLAT_TERRAIN)
    assert np.all(np.isnan(amap.sigma_pos2_m[:, flat]))
    assert np.all(amap.degenerate[:, flat])
    assert not amap.degenerate[:, rough].any()
    pos, att = amap.sigma_pos2_m[:, rough], amap.sigma_att2_deg[:, rough]
    assert np.all(np.isfinite(pos) & (pos > 0)) and np.all(np.isfinite(att) & (att > 0))
    # The nominal geometry of section VI: metres to tens of metres, about a degree.
    assert 1.0 < np.median(pos) < 50.0 and 0.1 < np.median(att) < 5.0


def test_a_node_equals_analyze_pair_run_by_hand(half_flat_dtm, amap):
    i, j = len(amap.y_m) // 2, len(amap.x_m) - 2  # a rough-side node
    x, y = float(amap.x_m[j]), float(amap.y_m[i])
    loc = accuracy_at(half_flat_dtm, x, y, SETTINGS)
    a = analyze_pair(loc.world_T_cam_a, loc.world_T_cam_b, loc.q_a, loc.q_b, loc.G_E, loc.N,
                     loc.noise)
    sigma_pos = math.sqrt(np.trace(a.sigma_c2_weighted[:3, :3]))
    sigma_att = math.degrees(math.sqrt(np.trace(a.sigma_c2_weighted[3:, 3:])))
    assert not a.degeneracy.degenerate
    assert amap.sigma_pos2_m[i, j] == pytest.approx(sigma_pos, rel=SAME_NUMBER_RTOL)
    assert amap.sigma_att2_deg[i, j] == pytest.approx(sigma_att, rel=SAME_NUMBER_RTOL)

    # ... and the pair there is the one the settings describe, with noiseless features.
    Ta, Tb = loc.world_T_cam_a, loc.world_T_cam_b
    np.testing.assert_allclose(Ta[:2, 3], [x, y])
    assert Ta[2, 3] == pytest.approx(np.nanmean(half_flat_dtm.elevation) + 500.0)
    assert np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]) == pytest.approx(SETTINGS.baseline_m)
    assert np.degrees(np.linalg.norm(so3_log(Ta[:3, :3].T @ Tb[:3, :3]))) == pytest.approx(
        SETTINGS.rotation_deg)
    assert Ta[2, 2] == pytest.approx(-1.0)  # optical axis straight down
    assert loc.q_a.shape[0] == SETTINGS.n_features == amap.n_features[i, j]
    g_b = (loc.G_E - Tb[:3, 3]) @ Tb[:3, :3]
    np.testing.assert_allclose(loc.q_b, g_b / g_b[:, 2:3], atol=REPROJECTION_TOL)
    np.testing.assert_allclose(half_flat_dtm.height(loc.G_E[:, 0], loc.G_E[:, 1]),
                               loc.G_E[:, 2], atol=1e-6)


def test_nodes_cover_the_dtm_at_the_step(half_flat_dtm, amap):
    x, y = map_nodes(half_flat_dtm, SETTINGS.step_m)
    np.testing.assert_array_equal(x, amap.x_m)
    assert np.allclose(np.diff(x), SETTINGS.step_m) and np.allclose(np.diff(y), SETTINGS.step_m)
    xmin, xmax, ymin, ymax = half_flat_dtm.bounds
    assert x[0] - SETTINGS.step_m / 2 >= xmin - 1e-9 and x[-1] + SETTINGS.step_m / 2 <= xmax + 1e-9
    assert amap.sigma_pos2_m.shape == (y.size, x.size)


def test_parallel_map_equals_serial(half_flat_dtm):
    small = AccuracyMapSettings(altitude_m=500.0, fov_deg=60.0, step_m=600.0, sigma_h_m=2.4)
    serial = accuracy_map(half_flat_dtm, small)
    two = accuracy_map(half_flat_dtm, small, ParallelSettings(workers=2))
    np.testing.assert_array_equal(serial.sigma_pos2_m, two.sigma_pos2_m)
    np.testing.assert_array_equal(serial.reason_codes, two.reason_codes)


def test_ground_altitude_reference_flies_over_the_ground(half_flat_dtm):
    s = AccuracyMapSettings(altitude_m=400.0, fov_deg=60.0,
                            altitude_reference=AltitudeReference.GROUND)
    loc = accuracy_at(half_flat_dtm, 600.0, 100.0, s)
    ground = float(half_flat_dtm.height(np.array(600.0), np.array(100.0)))
    assert loc.world_T_cam_a[2, 3] == pytest.approx(ground + 400.0)


def test_reason_codes_name_every_reason():
    code = DegeneracyCode.from_reasons(("flat_terrain", "ill_conditioned", "new_reason"))
    assert code == DegeneracyCode.FLAT_TERRAIN | DegeneracyCode.ILL_CONDITIONED | \
        DegeneracyCode.OTHER
    assert DEGENERACY_CODE_NAMES[int(math.log2(DegeneracyCode.FLAT_TERRAIN))] == "flat_terrain"


@pytest.mark.parametrize("change", [{"fov_deg": 0.0}, {"altitude_m": -5.0},
                                    {"n_features": 0}, {"step_m": 0.0}])
def test_bad_settings_are_user_errors(half_flat_dtm, change):
    kwargs = {"altitude_m": 500.0, "fov_deg": 60.0} | change
    with pytest.raises(CdtmError):
        accuracy_map(half_flat_dtm, AccuracyMapSettings(**kwargs))


@pytest.mark.parametrize("change, words", [
    ({"heading_deg": math.nan}, "heading_deg = nan, expected a finite angle in [-360, 360]"),
    ({"heading_deg": math.inf}, "heading_deg = inf, expected a finite angle"),
    ({"heading_deg": 361.0}, "heading_deg = 361.0, expected a finite angle"),
    ({"rotation_deg": 1e6}, "rotation_deg = 1000000.0, expected at most 180 deg"),
    ({"n_features": 100_001}, "n_features = 100001, expected 1 to 100000 features per pair"),
    ({"n_features": 10**400}, "n_features = 1000000000000000..., expected 1 to 100000"),
    ({"resolution_px": 1}, "resolution_px = 1, expected 2 to 100000 px"),
    ({"resolution_px": 100_001}, "resolution_px = 100001, expected 2 to 100000 px"),
])
def test_non_finite_or_oversized_settings_are_refused_up_front(change, words):
    settings = AccuracyMapSettings(**({"altitude_m": 500.0, "fov_deg": 60.0} | change))
    with pytest.raises(CdtmError) as info:
        settings.check()
    assert str(info.value) == words or str(info.value).startswith(words), str(info.value)


def test_cli_writes_npz_and_png(tmp_path, half_flat_dtm, capsys):
    dtm_path = tmp_path / "dtm.npz"
    save_dtm_npz(half_flat_dtm, dtm_path)
    out = tmp_path / "map"
    code = cdtm_main(["accuracy-map", str(dtm_path), "--alt-m", "500", "--fov-deg", "60",
                      "--step-m", "600", "--workers", "1", "--out", str(out)])
    assert code == 0
    with np.load(out / "accuracy_map.npz") as z:
        assert z["sigma_pos2_m"].shape == (z["y_m"].size, z["x_m"].size)
        np.testing.assert_array_equal(z["degenerate"], z["reason_codes"] != 0)
        assert z["degenerate"].any() and not z["degenerate"].all()
        assert tuple(z["reason_names"]) == DEGENERACY_CODE_NAMES
        assert float(z["fov_deg"]) == 60.0
    assert (out / "accuracy_map.png").read_bytes().startswith(b"\x89PNG")
    assert "degenerate nodes" in capsys.readouterr().out


def test_cli_missing_dtm_is_one_line(tmp_path, capsys):
    code = cdtm_main(["accuracy-map", str(tmp_path / "nope.npz"), "--alt-m", "500",
                      "--fov-deg", "60", "--out", str(tmp_path / "map")])
    assert code == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "map").exists()


@pytest.mark.parametrize("options, words", [
    (["--heading-deg", "nan"], "heading_deg = nan, expected a finite angle in [-360, 360] deg"),
    (["--heading-deg=-inf"], "heading_deg = -inf, expected a finite angle"),
    (["--features", "100000000000"],
     "n_features = 100000000000, expected 1 to 100000 features per pair"),
    (["--step-m", "1e-6"], "step_m = 1e-06 m makes about 2.4e+09 x 2.4e+09 nodes over the "
                           "DTM's 2400 x 2400 m; expected at most 1e+06 nodes: a larger step"),
    (["--step-m", "2"], "makes about 1.2e+03 x 1.2e+03 nodes"),
])
def test_cli_refuses_a_non_finite_or_oversized_option_in_one_line(tmp_path, half_flat_dtm,
                                                                  capsys, options, words):
    dtm_path = tmp_path / "dtm.npz"
    save_dtm_npz(half_flat_dtm, dtm_path)
    out = tmp_path / "map"
    code = cdtm_main(["accuracy-map", str(dtm_path), "--alt-m", "500", "--fov-deg", "60",
                      "--step-m", "600", "--workers", "1", *options, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith("cdtm accuracy-map: error: ") and words in err[0], err[0]
    assert not out.exists()


def test_map_nodes_refuses_a_grid_beyond_the_cap_before_allocating(half_flat_dtm):
    with pytest.raises(CdtmError, match=r"step_m = 1e-09 m makes about 2\.4e\+12 x"):
        map_nodes(half_flat_dtm, 1e-9)  # 5.8e24 nodes: np.arange would fail to allocate
    x, y = map_nodes(half_flat_dtm, 2.4)  # 1000 x 1000: the cap itself is accepted
    assert x.size * y.size == 1_000_000
