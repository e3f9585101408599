"""geometry.crs: user CRS parsing and the metric local ENU frame (checked against pyproj's ECEF)."""
import numpy as np
import pytest
from pyproj import Proj, Transformer

from geometry.crs import CRSInputError, LocalFrame, crs_from_user
from geometry.similarity import fit_similarity
from geometry.transforms import Sim3

UTM32 = np.array([512000.0, 5781000.0, 80.0])  # near 52.2°N, 9.2°E


def utm_site(rng, n=20, size=3000.0):
    return UTM32 + np.c_[rng.uniform(0, size, (n, 2)), rng.uniform(0, 60, n)]


@pytest.mark.parametrize("text, epsg", [("EPSG:32632", 32632), ("epsg:4326", 4326), ("25832", 25832),
                                        ("+proj=utm +zone=33 +datum=WGS84 +units=m +no_defs", None)])
def test_crs_from_user_accepts_common_forms(text, epsg):
    crs = crs_from_user(text)
    assert crs.to_epsg() == epsg or (epsg is None and crs.is_projected)


@pytest.mark.parametrize("text, word", [("EPSG:999999", "unknown CRS 'EPSG:999999'"),
                                        ("EPSG:abc", "must be a number"), ("", "empty CRS"),
                                        ("+proj=foo", "unknown CRS")])
def test_crs_from_user_errors_are_one_line(text, word):
    with pytest.raises(CRSInputError) as exc:
        crs_from_user(text)
    assert word in str(exc.value) and "\n" not in str(exc.value)


def test_utm_local_frame_roundtrip_and_metric_against_pyproj_ecef():
    rng = np.random.default_rng(0)
    pts = utm_site(rng)
    frame = LocalFrame.from_points(pts, crs_from_user("EPSG:32632"))
    assert frame.kind == "enu"
    local = frame.to_local(pts)
    assert local.dtype == np.float64
    np.testing.assert_allclose(frame.from_local(local), pts, atol=1e-6, rtol=0)
    np.testing.assert_allclose(frame.to_local(frame.origin), 0.0, atol=1e-6)
    # pairwise distances equal those of pyproj's own geocentric coordinates (independent path)
    to_ecef = Transformer.from_crs("EPSG:32632", "EPSG:4978", always_xy=True)
    ecef = np.stack(to_ecef.transform(*pts.T), axis=1)
    d_local = np.linalg.norm(local[:, None] - local[None], axis=2)
    d_ecef = np.linalg.norm(ecef[:, None] - ecef[None], axis=2)
    assert np.abs(d_local - d_ecef).max() < 1e-6
    # ... and differ from grid distances by the UTM scale factor (≈ 0.9996 near the central meridian)
    d_grid = np.linalg.norm(pts[:, None, :2] - pts[None, :, :2], axis=2)
    far = d_grid > 1000
    ratio = d_grid[far] / np.hypot(d_local[far], 0)
    assert 0.9994 < np.median(ratio) < 0.9998


def test_enu_axes_point_east_north_up():
    frame = LocalFrame(crs_from_user("EPSG:32632"), UTM32)
    up = frame.to_local(UTM32 + [0, 0, 10.0])[0]
    np.testing.assert_allclose(up, [0, 0, 10.0], atol=1e-6)
    # 100 grid metres north: ~100/k true metres north, a little below the tangent plane (earth curvature)
    north = frame.to_local(UTM32 + [0, 100.0, 0])[0]
    # grid north is turned from true north by the meridian convergence γ (pyproj's own figure)
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(*UTM32[:2])
    gamma = np.radians(Proj("EPSG:32632").get_factors(lon, lat).meridian_convergence)
    assert 0.1 < abs(north[0]) and abs(abs(north[0]) - 100.0 * np.sin(gamma)) < 0.005
    assert 100.0 < north[1] < 100.1
    assert -2e-3 < north[2] < -5e-4  # ≈ −d²/(2R) = −0.8 mm


def test_geographic_crs_uses_lon_lat_order():
    frame = LocalFrame(crs_from_user("EPSG:4326"), [9.17, 52.17, 80.0])
    east = frame.to_local([[9.171, 52.17, 80.0]])[0]  # +0.001° longitude
    expected = np.radians(0.001) * 6.39e6 * np.cos(np.radians(52.17))  # ≈ 68.5 m
    assert abs(east[0] - expected) < 0.5 and abs(east[1]) < 0.05
    np.testing.assert_allclose(frame.from_local(east[None]), [[9.171, 52.17, 80.0]], atol=1e-9)


def test_geocentric_and_plain_cartesian_frames():
    rng = np.random.default_rng(1)
    ecef = np.array([3870000.0, 614000.0, 5015000.0]) + rng.uniform(0, 500, (5, 3))
    frame = LocalFrame.from_points(ecef, crs_from_user("EPSG:4978"))
    local = frame.to_local(ecef)
    np.testing.assert_allclose(np.linalg.norm(local[0] - local[1]), np.linalg.norm(ecef[0] - ecef[1]), atol=1e-8)
    np.testing.assert_allclose(frame.from_local(local), ecef, atol=1e-8, rtol=0)
    plain = LocalFrame.from_points(ecef)
    assert plain.kind == "offset" and plain.to_dict()["crs"] is None
    np.testing.assert_array_equal(plain.to_local(ecef), ecef - ecef.mean(axis=0))


def test_millimetres_survive_in_the_local_frame():
    frame = LocalFrame(crs_from_user("EPSG:32632"), UTM32)
    a, b = frame.to_local([UTM32 + [1000.0, 1000.0, 0], UTM32 + [1000.001, 1000.0, 0]])
    assert 0.00099 < np.linalg.norm(b - a) < 0.00101


def test_fitting_in_local_frame_beats_fitting_in_easting_northing_height():
    """A metric model of a 3 km site fits the local frame exactly but not (E, N, h)."""
    rng = np.random.default_rng(2)
    pts = utm_site(rng, 40, 3000.0)
    frame = LocalFrame.from_points(pts, crs_from_user("EPSG:32632"))
    local = frame.to_local(pts)
    model = Sim3(0.2, np.eye(3), [1.0, 2, 3])(local)  # an arbitrary metric reconstruction frame
    assert fit_similarity(model, local).rms < 1e-6
    enh = fit_similarity(model, pts - pts.mean(axis=0))
    assert 0.01 < enh.rms < 1.0  # map-projection scale and earth curvature


def test_non_finite_points_rejected():
    with pytest.raises(CRSInputError):
        LocalFrame.from_points([[0, 0, np.nan]], None)
