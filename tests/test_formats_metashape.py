"""Metashape XML: camera export round trip, camera model conventions, chunk transform, markers, bad files."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cpdetect.errors import InputError
from cpdetect.formats.metashape import (MarkerRecord, camera_from_metashape, camera_to_metashape,
                                        markers_from_observations, read_metashape_cameras,
                                        read_metashape_markers, write_metashape_cameras,
                                        write_metashape_markers)
from cpdetect.formats.odm import GcpObservation
from cpdetect.formats.reconstruction import read_reconstruction
from geometry.camera import Camera
from geometry.scene import ImageRecord, Scene
from geometry.transforms import Rigid3, Sim3


def make_scene(rng) -> Scene:
    cams = {0: Camera(4000, 3000, 3000.0, 2990.0, 2010.3, 1490.2, (0.01, -0.02, 0.001, -0.002, 0.003)),
            3: Camera(1000, 800, 900.0, 900.0, 499.5, 399.5)}
    images = {}
    for i in range(5):
        R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        images[f"IMG_{i:04d}.JPG"] = ImageRecord(f"IMG_{i:04d}.JPG", 0 if i < 3 else 3,
                                                 Rigid3(R, rng.normal(size=3) * 100))
    chunk = Sim3(0.87, Rotation.from_rotvec([0.2, -1.0, 0.4]).as_matrix(), [4.0e6, 6.1e5, 4.9e6])
    return Scene(cams, images, meta={"chunk_transform": chunk, "crs_wkt": 'GEOGCS["WGS 84"]'})


def test_round_trip_scene_metashape_scene(tmp_path):
    scene = make_scene(np.random.default_rng(0))
    path = write_metashape_cameras(scene, tmp_path / "cameras.xml")
    back = read_metashape_cameras(path)
    assert list(back.images) == list(scene.images)
    for name, rec in scene.images.items():
        assert back.images[name].camera_id == rec.camera_id
        np.testing.assert_allclose(back.images[name].cam_from_world.matrix, rec.cam_from_world.matrix,
                                   atol=1e-9, rtol=0)
    for k, cam in scene.cameras.items():
        b = back.cameras[k]
        np.testing.assert_allclose([b.fx, b.fy, b.cx, b.cy], [cam.fx, cam.fy, cam.cx, cam.cy], atol=1e-9)
        np.testing.assert_allclose(b.dist, cam.dist, atol=1e-15)
    np.testing.assert_allclose(back.meta["chunk_transform"].matrix, scene.meta["chunk_transform"].matrix,
                               atol=1e-9, rtol=0)
    assert back.meta["crs_wkt"] == scene.meta["crs_wkt"]
    # The file stores camera -> chunk: the transform's translation is the camera centre.
    root = ET.parse(path).getroot()
    el = root.find("chunk/cameras/camera[@label='IMG_0000.JPG']/transform")
    M = np.array(el.text.split(), float).reshape(4, 4)
    np.testing.assert_allclose(M[:3, 3], scene.images["IMG_0000.JPG"].center, atol=1e-9)


def test_camera_labels_as_stems(tmp_path):
    scene = make_scene(np.random.default_rng(5))
    back = read_metashape_cameras(write_metashape_cameras(scene, tmp_path / "c.xml", camera_labels="stem"))
    assert list(back.images) == [n.rsplit(".", 1)[0] for n in scene.images]


def metashape_project(cal: dict, w: int, h: int, X: np.ndarray) -> np.ndarray:
    """The Metashape manual's frame camera formula, written out independently (corner pixel origin)."""
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r2 = x * x + y * y
    rad = 1 + cal["k1"] * r2 + cal["k2"] * r2 ** 2 + cal["k3"] * r2 ** 3
    xd = x * rad + cal["p1"] * (r2 + 2 * x * x) + 2 * cal["p2"] * x * y
    yd = y * rad + cal["p2"] * (r2 + 2 * y * y) + 2 * cal["p1"] * x * y
    u = w * 0.5 + cal["cx"] + xd * cal["f"] + xd * cal["b1"]
    v = h * 0.5 + cal["cy"] + yd * cal["f"]
    return np.stack([u, v], axis=1)


def test_camera_model_p1_p2_swap_and_centre_offsets():
    cal = {"f": 3000.0, "b1": 7.0, "cx": 12.5, "cy": -8.25, "k1": -0.05, "k2": 0.02, "k3": -0.004,
           "p1": 0.0012, "p2": -0.0031}
    cam = camera_from_metashape(4000, 3000, **cal)
    assert cam.dist[2:4] == (cal["p2"], cal["p1"])  # OpenCV (p1, p2) = Metashape (P2, P1)
    assert (cam.cx, cam.cy) == (2000 + 12.5 - 0.5, 1500 - 8.25 - 0.5)
    X = np.array([[0.3, -0.2, 2.0], [-0.4, 0.35, 1.5], [0.0, 0.0, 1.0], [0.1, 0.3, 1.2]])
    uv_cv, _ = cam.project(X)
    np.testing.assert_allclose(metashape_project(cal, 4000, 3000, X), uv_cv + 0.5, atol=1e-9)
    back = camera_to_metashape(cam)
    for k, v in cal.items():
        assert back[k] == pytest.approx(v, abs=1e-12)


def test_disabled_and_unaligned_cameras_skipped_and_old_chunk_transform(tmp_path):
    xml = """<?xml version="1.0" encoding="UTF-8"?>
<document version="1.4.0">
  <chunk label="c">
    <sensors><sensor id="0" label="s" type="frame">
      <resolution width="100" height="80"/>
      <calibration type="frame" class="adjusted"><resolution width="100" height="80"/>
        <f>90</f><cx>1</cx><cy>-1</cy><p1>0.01</p1></calibration></sensor></sensors>
    <cameras>
      <camera id="0" sensor_id="0" label="a"><transform>1 0 0 5 0 1 0 6 0 0 1 7 0 0 0 1</transform></camera>
      <group id="0" label="g" type="folder">
        <camera id="1" sensor_id="0" label="b" enabled="false"><transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform></camera>
        <camera id="2" sensor_id="0" label="c"/>
        <camera id="3" sensor_id="0" label="d"><transform>1 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1</transform></camera>
      </group>
    </cameras>
    <transform><rotation>0 -1 0 1 0 0 0 0 1</rotation><translation>10 20 30</translation><scale>2</scale></transform>
  </chunk>
</document>
"""
    p = tmp_path / "old.xml"
    p.write_text(xml)
    s = read_metashape_cameras(p)
    assert list(s.images) == ["a", "d"]
    np.testing.assert_allclose(s.images["a"].center, [5, 6, 7])
    cam = s.cameras[0]
    assert (cam.cx, cam.cy, cam.dist[3]) == (50.5, 38.5, 0.01)
    sim = s.meta["chunk_transform"]
    np.testing.assert_allclose(sim([1.0, 0.0, 0.0]), [10, 22, 30])  # 2 * Rz(90) * x + t
    assert "crs_wkt" not in s.meta


def test_markers_round_trip_and_pixel_convention(tmp_path):
    scene = make_scene(np.random.default_rng(1))
    markers = [MarkerRecord("GCP1", [651234.125, 5237001.5, 101.25],
                            {"IMG_0000.JPG": (100.0, 200.25), "IMG_0002.JPG": (3000.5, 10.0)}),
               MarkerRecord("GCP2", [651300.0, 5237100.0, 99.0], {"IMG_0001.JPG": (5.0, 6.0)}),
               MarkerRecord("check", None, {"IMG_0004.JPG": (0.0, 0.0)})]
    p = write_metashape_markers(tmp_path / "markers.xml", markers, scene, crs="EPSG:32632")
    root = ET.parse(p).getroot()
    loc = root.find("chunk/frames/frame/markers/marker[@marker_id='0']/location")
    assert (float(loc.get("x")), float(loc.get("y"))) == (100.5, 200.75)  # corner convention on disk
    assert {c.get("label") for c in root.iter("camera")} == {"IMG_0000", "IMG_0001", "IMG_0002", "IMG_0004"}
    assert 'AUTHORITY["EPSG","32632"]' in root.find("chunk/reference").text
    back = read_metashape_markers(p)
    assert [m.label for m in back.markers] == ["GCP1", "GCP2", "check"]
    np.testing.assert_array_equal(back.markers[0].reference, markers[0].reference)
    assert back.markers[0].projections == {"IMG_0000": (100.0, 200.25), "IMG_0002": (3000.5, 10.0)}
    assert back.markers[2].reference is None
    pts = back.survey_points()
    assert list(pts) == ["GCP1", "GCP2"]
    assert back.crs().to_epsg() == 32632
    with pytest.raises(ValueError, match="not in the scene"):
        write_metashape_markers(tmp_path / "m2.xml", [MarkerRecord("x", None, {"nope.jpg": (1, 2)})], scene)


def test_markers_from_gcp_observations(tmp_path):
    obs = [GcpObservation([1, 2, 3], 10, 20, "a.jpg", "g1"), GcpObservation([1, 2, 3], 11, 21, "b.jpg", "g1"),
           GcpObservation([4, 5, 6], 12, 22, "a.jpg", "g2")]
    ms = markers_from_observations(obs)
    assert [(m.label, len(m.projections)) for m in ms] == [("g1", 2), ("g2", 1)]
    back = read_metashape_markers(write_metashape_markers(tmp_path / "m.xml", ms, camera_labels="name"))
    assert back.markers[0].projections == {"a.jpg": (10.0, 20.0), "b.jpg": (11.0, 21.0)}
    np.testing.assert_array_equal(back.survey_points()["g2"], [4, 5, 6])


def test_truncated_xml_names_file_and_line(tmp_path):
    scene = make_scene(np.random.default_rng(2))
    text = write_metashape_cameras(scene, tmp_path / "c.xml").read_text()
    cut = "\n".join(text.splitlines()[:20])
    p = tmp_path / "cut.xml"
    p.write_text(cut)
    with pytest.raises(InputError) as ei:
        read_metashape_cameras(p)
    assert ei.value.path == str(p) and ei.value.line == 20 and "invalid XML" in str(ei.value)
    assert "\n" not in str(ei.value)


@pytest.mark.parametrize("body, line, match", [
    ('<sensors><sensor id="0" type="fisheye"><resolution width="10" height="10"/>\n'
     '<calibration type="fisheye"><f>5</f></calibration></sensor></sensors><cameras/>', 2, "not supported"),
    ('<sensors><sensor id="0"><resolution width="10" height="10"/><calibration>\n'
     '<f>5</f><b2>0.1</b2></calibration></sensor></sensors><cameras/>', 3, "b2"),
    ('<sensors><sensor id="0"><resolution width="10" height="10"/><calibration><f>5</f></calibration>\n'
     '</sensor></sensors><cameras><camera id="0" sensor_id="0" label="a">\n'
     '<transform>1 0 0 0 0 1 0 0 0 0 1 nan 0 0 0 1</transform></camera></cameras>', 4, "not finite"),
    ('<sensors><sensor id="0"><resolution width="10" height="10"/><calibration><f>5</f></calibration>\n'
     '</sensor></sensors><cameras><camera id="0" sensor_id="0" label="a">\n'
     '<transform>2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform></camera></cameras>', 4, "not rigid"),
    ('<sensors/><cameras><camera id="0" sensor_id="4" label="a">\n'
     '<transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform></camera></cameras>', 2, "sensor 4"),
])
def test_bad_content_names_line(tmp_path, body, line, match):
    p = tmp_path / "bad.xml"
    p.write_text(f'<?xml version="1.0"?>\n<document><chunk>{body}</chunk></document>\n')
    with pytest.raises(InputError, match=match) as ei:
        read_metashape_cameras(p)
    assert (ei.value.path, ei.value.line) == (str(p), line)


def test_not_metashape_and_missing(tmp_path):
    p = tmp_path / "x.xml"
    p.write_text("<svg></svg>")
    with pytest.raises(InputError, match="not a Metashape"):
        read_metashape_cameras(p)
    with pytest.raises(InputError, match="not found"):
        read_metashape_markers(tmp_path / "none.xml")


def test_read_reconstruction_detects_metashape(tmp_path):
    scene = make_scene(np.random.default_rng(4))
    got = read_reconstruction(write_metashape_cameras(scene, tmp_path / "cams.xml"))
    assert got.meta["format"] == "metashape" and list(got.images) == list(scene.images)
    assert got.meta["ecef_from_model"] is got.meta["chunk_transform"]
    # A forced format skips detection (a Metashape export saved without the .xml suffix).
    (tmp_path / "cams.export").write_bytes((tmp_path / "cams.xml").read_bytes())
    assert read_reconstruction(tmp_path / "cams.export", fmt="metashape").meta["format"] == "metashape"
    with pytest.raises(InputError, match="unknown reconstruction format"):
        read_reconstruction(tmp_path / "cams.export")
    from cpdetect.errors import UsageError

    with pytest.raises(UsageError, match="valid: colmap, metashape, opensfm"):
        read_reconstruction(tmp_path / "cams.xml", fmt="bundler")


def test_entity_declarations_refused(tmp_path):
    p = tmp_path / "e.xml"
    p.write_text('<?xml version="1.0"?>\n<!DOCTYPE d [<!ENTITY a "aaaaaaaaaa">\n<!ENTITY b "&a;&a;&a;">]>\n'
                 "<document><chunk>&b;</chunk></document>\n")
    with pytest.raises(InputError, match="entity declarations") as ei:
        read_metashape_markers(p)
    assert ei.value.line == 2


@pytest.mark.parametrize("code", ["EPSG:4979", "EPSG:32632+5773", "EPSG:2056"])
def test_markers_crs_objects_written_as_wkt(tmp_path, code):
    from pyproj import CRS

    crs = CRS.from_user_input(code)
    p = write_metashape_markers(tmp_path / "m.xml", [MarkerRecord("a", [1.0, 2.0, 3.0])], crs=crs)
    assert read_metashape_markers(p).crs().equals(crs)
