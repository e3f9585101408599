"""ODM gcp_list.txt: header forms, round trip, pixel convention, survey points, bad files."""
from __future__ import annotations

import numpy as np
import pytest
from pyproj import CRS, Transformer

from cpdetect.errors import InputError, UsageError
from cpdetect.formats.odm import (PIXEL_SHIFT, GcpObservation, crs_header, gcp_survey_points, parse_crs,
                                  read_gcp_list, write_gcp_list)


def observations(rng):
    out = []
    for k in range(4):
        geo = np.array([650_000.0, 5_237_000.0, 100.0]) + rng.uniform(-300, 300, 3)
        for img in range(3):
            out.append(GcpObservation(geo, *rng.uniform(0, 4000, 2), f"DJI_{img:04d}.JPG", f"gcp{k}",
                                      ("extra1",) if k == 0 else ()))
    return out


def test_round_trip_same_values(tmp_path):
    obs = observations(np.random.default_rng(0))
    p = write_gcp_list(tmp_path / "gcp_list.txt", "EPSG:32632", obs)
    g = read_gcp_list(p)
    assert g.header == "EPSG:32632" and g.crs.to_epsg() == 32632
    assert g.observations == obs  # float64 values, names and extras identical (no rounding on the way)
    assert [o.line for o in g.observations] == list(range(2, 2 + len(obs)))
    for a, b in zip(obs, g.observations):
        np.testing.assert_array_equal(a.geo, b.geo)
        assert (a.im_x, a.im_y) == (b.im_x, b.im_y)
    # The text itself is the documented layout.
    first = p.read_text().splitlines()[1].split()
    assert first[5:] == ["DJI_0000.JPG", "gcp0", "extra1"] and float(first[3]) == obs[0].im_x
    # A CRS object is written as its EPSG code.
    p2 = write_gcp_list(tmp_path / "g2.txt", CRS.from_epsg(4326), obs[:1])
    assert p2.read_text().splitlines()[0] == "EPSG:4326"


def test_header_forms():
    assert parse_crs("EPSG:32632").to_epsg() == 32632
    assert parse_crs("epsg:2056").to_epsg() == 2056
    assert parse_crs("WGS84 UTM 32N").to_epsg() == 32632
    assert parse_crs("WGS84 UTM 19S").to_epsg() == 32719
    assert parse_crs("WGS84").to_epsg() == 4326
    proj = parse_crs("+proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs")
    # Same projection as EPSG:32610: a point maps to the same easting/northing.
    a = Transformer.from_crs(4326, proj, always_xy=True).transform(-123.0, 45.0)
    b = Transformer.from_crs(4326, 32610, always_xy=True).transform(-123.0, 45.0)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert crs_header(proj).startswith("+proj=utm") or crs_header(proj) == "EPSG:32610"
    with pytest.raises(UsageError, match="unknown or invalid CRS"):
        parse_crs("EPSG:999999", error=UsageError)


def test_bom_comments_blank_lines_and_missing_name(tmp_path):
    p = tmp_path / "gcp_list.txt"
    p.write_bytes("\ufeffWGS84 UTM 32N\n# a comment\n\n"
                  "500000.5\t5700000.25  101.5 10 20.5 a.jpg\n"
                  "500000.5 5700000.25 101.5 30 40 b.jpg\n"
                  "500010 5700000 99 1 2 a.jpg p2 \n".encode())
    g = read_gcp_list(p)
    assert g.crs.to_epsg() == 32632 and len(g.observations) == 3
    o = g.observations[0]
    assert (o.image, o.name, o.im_x, o.im_y, o.line) == ("a.jpg", None, 10.0, 20.5, 4)
    pts = gcp_survey_points(g)
    assert list(pts) == ["unnamed-1", "p2"]
    np.testing.assert_array_equal(pts["unnamed-1"], [500000.5, 5700000.25, 101.5])


def test_epsg4326_geo_x_is_longitude(tmp_path):
    p = tmp_path / "g.txt"
    p.write_text("EPSG:4326\n8.727 52.197 120.0 100 200 x.jpg g1\n")
    g = read_gcp_list(p)
    lon, lat, _ = g.observations[0].geo
    e, n = Transformer.from_crs(g.crs, 32632, always_xy=True).transform(lon, lat)
    # 0.273 deg west of the 9E central meridian at 52.2N is about 18.6 km west of easting 500 km.
    assert 480_000 < e < 483_000 and 5_780_000 < n < 5_790_000


def test_pixel_convention_is_opensfm_normalisation():
    """ODM runs OpenSfM, whose normalisation puts the image centre at pixel ((w-1)/2, (h-1)/2):
    top-left pixel centre = (0, 0) as in OpenCV, so no shift is applied."""
    assert PIXEL_SHIFT == 0.0
    w, h = 4000, 3000

    def opensfm_normalised(x, y):  # features.normalized_image_coordinates
        size = max(w, h)
        return (x + 0.5 - w / 2.0) / size, (y + 0.5 - h / 2.0) / size

    assert opensfm_normalised((w - 1) / 2 + PIXEL_SHIFT, (h - 1) / 2 + PIXEL_SHIFT) == (0.0, 0.0)


def test_inconsistent_coordinates_for_a_name(tmp_path):
    p = tmp_path / "g.txt"
    p.write_text("EPSG:32632\n1 2 3 10 10 a.jpg g1\n1 2 3.5 10 10 b.jpg g1\n")
    with pytest.raises(InputError) as ei:
        gcp_survey_points(read_gcp_list(p))
    assert (ei.value.path, ei.value.line) == (str(p), 3)


@pytest.mark.parametrize("text, line, match", [
    ("EPSG:999999\n1 2 3 4 5 a.jpg\n", 1, "unknown or invalid CRS"),
    ("650530.7 237530.4 104 3206 2391 DJI_0172.JPG 9\n", 1, "not a CRS header"),
    ("EPSG:32632\n1 2 3 4 5\n", 2, "malformed GCP line"),
    ("EPSG:32632\n1 2 3 4 5 a.jpg\n1 2 x 4 5 a.jpg\n", 3, "geo_z is not a number"),
    ("EPSG:32632\n1 2 nan 4 5 a.jpg\n", 2, "not finite"),
    ("EPSG:32632\n# only a comment\n", 2, "no observation"),
    ("WGS84 UTM 61N\n1 2 3 4 5 a.jpg\n", 1, "zone 61"),
    ("", 1, "empty"),
])
def test_bad_files_one_line_error(tmp_path, text, line, match):
    p = tmp_path / "gcp_list.txt"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as ei:
        read_gcp_list(p)
    assert (ei.value.path, ei.value.line) == (str(p), line)
    assert "\n" not in str(ei.value) and str(ei.value).startswith(f"{p}:{line}: ")


def test_missing_file_and_bad_names(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_gcp_list(tmp_path / "none.txt")
    bad = [GcpObservation([1, 2, 3], 1, 2, "my image.jpg", "g")]
    with pytest.raises(ValueError, match="blanks"):
        write_gcp_list(tmp_path / "g.txt", "EPSG:32632", bad)
    with pytest.raises(InputError):
        write_gcp_list(tmp_path / "g.txt", "not a crs", [])
    assert not (tmp_path / "g.txt").exists()
    assert list(tmp_path.iterdir()) == []  # nothing half-written
