"""geometry.registration (correspondence-free pairing + world_from_model) and ``cpdetect register``."""
import json

import numpy as np
import pytest

from cpdetect.cli import main as cli_main
from geometry.registration import (RandomTriplets, RegistrationConfig, TripletIndex, plain_ransac,
                                   register_points, simulate_detections)
from geometry.transforms import Sim3

NOISE, SURVEY_NOISE = 0.01, 0.003
SIGMA = np.hypot(NOISE, SURVEY_NOISE)  # per-axis std of (surveyed − transformed detected)

RECTANGLE = np.array([[0, 0, 0], [2.0, 0, 0], [2.0, 1.2, 0], [0, 1.2, 0]])
TABLE = np.array([[0, 0, 0.75], [1.6, 0, 0.75], [1.6, 0.9, 0.75], [0, 0.9, 0.75],
                  [0.1, 0.1, 0], [1.5, 0.1, 0], [1.5, 0.8, 0], [0.1, 0.8, 0]])
PIER = np.array([[0, 0, 0], [3.1, 0.2, 0.5], [5.7, -0.4, 1.9], [1.2, 2.8, 3.3], [4.4, 3.1, 0.7],
                 [6.3, 2.2, 4.1], [0.5, 5.2, 2.2], [3.3, 6.1, 5.0], [6.8, 5.5, 1.1]])


def site(rng, m=50, box=(100, 100, 20)):
    return rng.uniform([0, 0, 0], box, (m, 3))


def assert_proper(sim: Sim3):
    np.testing.assert_allclose(sim.R @ sim.R.T, np.eye(3), atol=1e-10)
    assert abs(np.linalg.det(sim.R) - 1) < 1e-10
    x = np.random.default_rng(0).normal(0, 50, (10, 3))
    np.testing.assert_allclose(sim.inverse()(sim(x)), x, atol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_50_surveyed_40_detected_exact_pairing_and_bounded_errors(seed):
    rng = np.random.default_rng(seed)
    prob = simulate_detections(site(rng), rng, n_seen=30, n_false=10, noise=NOISE, survey_noise=SURVEY_NOISE)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ok", r.reason
    assert r.pairing() == prob.true_pairing()
    assert sorted(r.unmatched_detected) == sorted(np.nonzero(prob.labels < 0)[0].tolist())
    assert len(r.unmatched_surveyed) == 20
    assert not r.alternatives
    assert_proper(r.world_from_model)
    # rms of 30 pair residuals: σ·sqrt(3 − 7/30) expected; two-sided (0 would mean leaked truth)
    expected = SIGMA * np.sqrt(3 - 7 / 30)
    assert 0.7 * expected < r.rms_m < 1.3 * expected
    assert 0.7 * SIGMA < r.sigma_m < 1.3 * SIGMA
    # scale: first-order std σ / (s·sqrt(Σ|x − x̄|²)) over ~30 points spread over ~100 m: ~1e-5
    rel = abs(r.world_from_model.scale / prob.truth.scale - 1)
    assert 0 < rel < 2e-4
    # the recovered transform puts the model points where the truth does, to about the noise
    err = np.linalg.norm(r.world_from_model(prob.detected) - prob.truth(prob.detected), axis=1)
    assert 1e-5 < np.median(err) < 2 * NOISE
    assert r.tolerance_m == pytest.approx(6 * r.sigma_m, rel=0.35)
    assert 0 < r.chance_probability < 1e-3


def test_explicit_tolerance_is_used_and_large_offsets_are_fine():
    rng = np.random.default_rng(11)
    sur = site(rng, 30) + [512000.0, 5781000.0, 80.0]  # UTM-sized numbers
    prob = simulate_detections(sur, rng, n_seen=20, n_false=5, noise=0.005)
    r = register_points(prob.detected, prob.surveyed, rng=rng, config=RegistrationConfig(tolerance=0.03))
    assert r.status == "ok" and r.pairing() == prob.true_pairing()
    assert r.tolerance_m == 0.03
    assert 0.5 * 0.005 * np.sqrt(3) < r.rms_m < 1.5 * 0.005 * np.sqrt(3)
    err = np.linalg.norm(r.world_from_model(prob.detected) - prob.truth(prob.detected), axis=1)
    assert 1e-5 < np.median(err) < 0.02


def test_tolerance_adapts_to_noise_larger_than_assumed():
    """Default config assumes 1 cm; with 2.5 cm of noise the tolerance grows with the residuals."""
    rng = np.random.default_rng(21)
    prob = simulate_detections(site(rng), rng, n_seen=30, n_false=10, noise=0.025, survey_noise=SURVEY_NOISE)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ok" and r.pairing() == prob.true_pairing()
    sigma = np.hypot(0.025, SURVEY_NOISE)
    assert 0.7 * sigma < r.sigma_m < 1.3 * sigma
    assert r.tolerance_m > RegistrationConfig().initial_tolerance


def test_large_sets_use_nearest_neighbour_triangles():
    rng = np.random.default_rng(22)
    config = RegistrationConfig()
    prob = simulate_detections(site(rng, 80, (200, 200, 20)), rng, n_seen=50, n_false=15, noise=NOISE)
    assert len(prob.surveyed) > config.full_index_limit
    r = register_points(prob.detected, prob.surveyed, rng=rng, config=config)
    assert r.status == "ok" and r.pairing() == prob.true_pairing()


def test_same_rng_seed_same_result():
    rng = np.random.default_rng(3)
    prob = simulate_detections(site(rng, 20), rng, n_seen=15, n_false=3)
    a = register_points(prob.detected, prob.surveyed, rng=np.random.default_rng(7))
    b = register_points(prob.detected, prob.surveyed, rng=np.random.default_rng(7))
    assert a.pairs == b.pairs and a.hypotheses_tried == b.hypotheses_tried
    np.testing.assert_array_equal(a.world_from_model.matrix, b.world_from_model.matrix)


def test_rectangle_is_ambiguous_with_its_three_rotations():
    rng = np.random.default_rng(4)
    prob = simulate_detections(RECTANGLE, rng, noise=0.003)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ambiguous"
    assert "different pairing" in r.reason
    # proper rotations of a planar rectangle: C2 about its normal and about both in-plane axes
    assert len(r.alternatives) == 3
    best = r.pairing()
    assert best == prob.true_pairing() or any(dict(a.pairs) == prob.true_pairing() for a in r.alternatives)
    for a in r.alternatives:
        assert a.n_inliers == 4 and a.rms < 0.02
        alt = dict(a.pairs)
        assert set(alt) == set(best) and alt != best  # same detected points, other surveyed points
        assert_proper(a.world_from_model)


def test_table_is_ambiguous_also_with_unseen_legs():
    rng = np.random.default_rng(5)
    for seen in (None, [0, 1, 2, 4, 5, 7]):
        prob = simulate_detections(TABLE, rng, noise=0.003, seen=seen)
        r = register_points(prob.detected, prob.surveyed, rng=rng)
        assert r.status == "ambiguous", r.reason
        assert len(r.alternatives) == 1  # the half turn about the vertical axis
        assert r.world_from_model is not None and len(r.pairs) == len(prob.detected)


def test_asymmetric_pier_is_ok_with_false_and_missed_points():
    rng = np.random.default_rng(6)
    prob = simulate_detections(PIER, rng, noise=0.003, seen=[0, 1, 2, 3, 5, 6, 8], n_false=2)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ok", r.reason
    assert r.pairing() == prob.true_pairing()
    assert r.unmatched_surveyed == [4, 7]


def test_mirror_symmetric_3d_layout_is_not_ambiguous_but_planar_one_is():
    rng = np.random.default_rng(7)
    half = np.array([[2, 0, 0.5], [5, 3, 2.0], [3, 7, 4.0], [6, -4, 1.0]])
    mirror3d = np.vstack([half, half * [-1, 1, 1], [[0, 9, 3]]])
    prob = simulate_detections(mirror3d, rng, noise=0.003)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ok" and r.pairing() == prob.true_pairing()
    planar = mirror3d * [1, 1, 0]  # flipping a plane over is a proper rotation
    prob = simulate_detections(planar, rng, noise=0.003)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ambiguous" and len(r.alternatives) == 1


@pytest.mark.parametrize("surveyed, detected, word", [
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 0, 0]], None, "collinear"),
    ([[1, 1, 1]] * 5, None, "coincident"),
    ([[0, 0, 0], [1, 0, 0]], None, "at least 3"),
    (PIER, PIER[:2], "at least 3"),
    (PIER, [[0, 0, 0], [1, 1, 1], [2, 2, 2]], "collinear"),
    ([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0.01]], None, "coincident"),
])
def test_degenerate_inputs_fail_with_a_reason(surveyed, detected, word):
    rng = np.random.default_rng(8)
    sur = np.asarray(surveyed, float)
    det = sur * 3 + 1 if detected is None else np.asarray(detected, float)
    r = register_points(det, sur, rng=rng)
    assert r.status == "failed" and r.world_from_model is None
    assert word in r.reason
    assert not r.pairs and np.isnan(r.rms_m)


def test_unrelated_points_fail_as_no_consistent_pairing():
    rng = np.random.default_rng(9)
    r = register_points(rng.uniform(0, 10, (12, 3)), site(rng, 15), rng=rng)
    assert r.status == "failed"
    assert "no consistent pairing" in r.reason
    assert r.hypotheses_tried > 0


def test_three_points_only_is_ok_but_says_nothing_checks_it():
    rng = np.random.default_rng(10)
    tri = np.array([[0, 0, 0], [3, 0, 0], [0.5, 2, 0.3]])
    prob = simulate_detections(tri, rng, noise=0.001)
    r = register_points(prob.detected, prob.surveyed, rng=rng)
    assert r.status == "ok" and r.pairing() == prob.true_pairing()
    assert "only 3 pairs" in r.reason


def test_shape_errors_raise():
    with pytest.raises(ValueError):
        register_points(np.zeros((5, 2)), np.zeros((5, 3)), rng=np.random.default_rng(0))


def test_generators_are_pluggable_over_one_core():
    rng = np.random.default_rng(12)
    prob = simulate_detections(site(rng, 12), rng, n_seen=10, n_false=2)
    truth = prob.true_pairing()
    det3 = list(truth)[:3]

    class Oracle:
        name = "oracle"

        def bound(self, problem):
            return 1.0

        def batches(self, problem, rng):
            yield np.array([[det3, [truth[d] for d in det3]]])

    r = register_points(prob.detected, prob.surveyed, rng=rng, generator=Oracle())
    assert r.status == "ok" and r.pairing() == truth and r.generator == "oracle"

    class Nothing(Oracle):
        def batches(self, problem, rng):
            return iter(())

    r = register_points(prob.detected, prob.surveyed, rng=rng, generator=Nothing())
    assert r.status == "failed" and "no consistent pairing" in r.reason
    # the index and the paper's plain RANSAC agree on a small problem
    a = register_points(prob.detected, prob.surveyed, rng=rng, generator=TripletIndex())
    b = plain_ransac(prob.detected, prob.surveyed, rng=np.random.default_rng(1), max_hypotheses=200_000)
    assert a.pairing() == b.pairing() == truth
    assert b.generator == RandomTriplets().name


# ------------------------------------------------------------------------------------------------
# CLI


def write_csv(path, header, names, xyz):
    lines = [header] + [f"{n},{x!r},{y!r},{z!r}" for n, (x, y, z) in zip(names, np.asarray(xyz).tolist())]
    path.write_text("\n".join(lines) + "\n")
    return path


def cli_problem(tmp_path, rng, surveyed, offset=(0.0, 0.0, 0.0), **kw):
    prob = simulate_detections(surveyed, rng, **kw)
    names = [f"GCP{i}" for i in range(len(surveyed))]
    det = write_csv(tmp_path / "det.csv", "id,x,y,z", [f"d{i}" for i in range(len(prob.detected))], prob.detected)
    sur = write_csv(tmp_path / "gcps.csv", "name,x,y,z,code", names, prob.surveyed + offset)
    sur.write_text(sur.read_text().replace("\n", ",A\n").replace("z,code,A", "z,code", 1))
    return prob, det, sur, names


def test_cli_ok_writes_registration_json(tmp_path, capsys):
    rng = np.random.default_rng(13)
    offset = np.array([500000.0, 5780000.0, 50.0])
    prob, det, sur, names = cli_problem(tmp_path, rng, site(rng, 20), offset, n_seen=15, n_false=3, noise=0.005)
    out = tmp_path / "reg.json"
    assert cli_main(["register", "--detected", str(det), "--surveyed", str(sur), "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["format"] == "cpdetect.registration/1" and d["status"] == "ok" and d["world"] == "surveyed"
    assert {p["detected"]: p["surveyed"] for p in d["pairs"]} == {
        f"d{i}": names[j] for i, j in prob.true_pairing().items()}
    assert len(d["unmatched_detected"]) == 3 and len(d["unmatched_surveyed"]) == 5
    sim = Sim3.from_matrix(np.array(d["matrix"]))
    assert sim.scale == pytest.approx(d["scale"], rel=1e-12)
    # "world" = the surveyed coordinates as given (offset included)
    expected = prob.truth(prob.detected) + offset
    assert np.abs(sim(prob.detected) - expected).max() < 0.05
    assert 0 < d["rms_m"] < 0.02 and d["alternatives"] == []


def test_cli_with_crs_fits_in_local_enu_frame(tmp_path):
    from geometry.crs import LocalFrame, crs_from_user

    rng = np.random.default_rng(14)
    local_true = site(rng, 15, (300, 300, 10))
    frame = LocalFrame.from_points(np.array([[512000.0, 5781000.0, 80.0]]), crs_from_user("EPSG:32632"))
    utm = frame.from_local(local_true)
    prob, det, sur, names = cli_problem(tmp_path, rng, utm, n_seen=12, n_false=2, noise=0.005)
    out = tmp_path / "reg.json"
    assert cli_main(["register", "--detected", str(det), "--surveyed", str(sur), "--crs", "EPSG:32632",
                     "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["world"] == "local_frame" and d["local_frame"]["crs"] == "EPSG:32632"
    assert d["local_frame"]["kind"] == "enu"
    # world_from_model maps into the local frame; the local frame maps back to UTM
    lf = LocalFrame(crs_from_user("EPSG:32632"), d["local_frame"]["origin"])
    sim = Sim3.from_dict(d)
    back = lf.from_local(sim(prob.detected[list(prob.true_pairing())]))
    truth_utm = utm[list(prob.true_pairing().values())]
    assert np.abs(back - truth_utm).max() < 0.05


def test_cli_reads_odm_gcp_list_with_its_crs(tmp_path):
    rng = np.random.default_rng(15)
    sur = site(rng, 12) + [512000.0, 5781000.0, 80.0]
    prob = simulate_detections(sur, rng, n_seen=10, n_false=1, noise=0.005)
    write_csv(tmp_path / "det.csv", "id,x,y,z", range(len(prob.detected)), prob.detected)
    lines = ["EPSG:32632"] + [f"{x!r} {y!r} {z!r} 100 200 IMG_{i}.JPG G{i}" for i, (x, y, z) in enumerate(sur.tolist())]
    (tmp_path / "gcp_list.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "reg.json"
    rc = cli_main(["register", "--detected", str(tmp_path / "det.csv"), "--surveyed", str(tmp_path / "gcp_list.txt"),
                   "--out", str(out)])
    d = json.loads(out.read_text())
    assert rc == 0 and d["status"] == "ok" and d["local_frame"]["crs"] == "EPSG:32632"
    assert {p["detected"]: p["surveyed"] for p in d["pairs"]} == {str(i): f"G{j}" for i, j in prob.true_pairing().items()}
    # a --crs that contradicts the header is a usage error
    rc = cli_main(["register", "--detected", str(tmp_path / "det.csv"), "--surveyed", str(tmp_path / "gcp_list.txt"),
                   "--crs", "EPSG:32633", "--out", str(tmp_path / "other.json")])
    assert rc == 2 and not (tmp_path / "other.json").exists()


def test_cli_ambiguous_and_failed_exit_3_with_json(tmp_path):
    rng = np.random.default_rng(16)
    prob, det, sur, _ = cli_problem(tmp_path, rng, RECTANGLE, noise=0.003)
    out = tmp_path / "reg.json"
    assert cli_main(["register", "--detected", str(det), "--surveyed", str(sur), "--out", str(out)]) == 3
    d = json.loads(out.read_text())
    assert d["status"] == "ambiguous" and len(d["alternatives"]) == 3
    assert all(len(a["matrix"]) == 4 and a["n_pairs"] == 4 for a in d["alternatives"])
    collinear = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [4, 0, 0.0]])
    write_csv(sur, "name,x,y,z", "ABCD", collinear)
    assert cli_main(["register", "--detected", str(det), "--surveyed", str(sur), "--out", str(out)]) == 3
    d = json.loads(out.read_text())
    assert d["status"] == "failed" and "collinear" in d["reason"] and d["matrix"] is None


@pytest.mark.parametrize("content, crs, expect", [
    ("name,x,y,z\nA,1,2,3\nB,4,5,nan\nC,0,0,1\n", None, "gcps.csv:3: z of 'B' is not finite"),
    ("name,x,y,z\nA,1,2,3\nB,4,5,6\n", None, "need at least 3 surveyed points"),
    ("name,x,y,z\nA,1,2,3\nB,4,5,6\nC,0,0,1\n", "EPSG:999999", "unknown CRS 'EPSG:999999'"),
])
def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys, content, crs, expect):
    det = write_csv(tmp_path / "det.csv", "id,x,y,z", "abc", [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    (tmp_path / "gcps.csv").write_text(content)
    args = ["register", "--detected", str(det), "--surveyed", str(tmp_path / "gcps.csv"),
            "--out", str(tmp_path / "reg.json")] + (["--crs", crs] if crs else [])
    assert cli_main(args) == 2
    err = capsys.readouterr().err.strip()
    assert expect in err and len(err.splitlines()) == 1
    assert not (tmp_path / "reg.json").exists()


def test_cli_reads_metashape_markers_with_chunk_crs(tmp_path):
    from cpdetect.formats.metashape import MarkerRecord, write_metashape_markers

    rng = np.random.default_rng(17)
    sur = site(rng, 10) + [512000.0, 5781000.0, 80.0]
    prob = simulate_detections(sur, rng, n_seen=8, n_false=1, noise=0.005)
    write_csv(tmp_path / "det.csv", "id,x,y,z", range(len(prob.detected)), prob.detected)
    write_metashape_markers(tmp_path / "markers.xml", [MarkerRecord(f"M{i}", p) for i, p in enumerate(sur)],
                            crs="EPSG:32632")
    out = tmp_path / "reg.json"
    rc = cli_main(["register", "--detected", str(tmp_path / "det.csv"), "--surveyed", str(tmp_path / "markers.xml"),
                   "--out", str(out)])
    d = json.loads(out.read_text())
    assert rc == 0 and d["status"] == "ok" and d["world"] == "local_frame"
    assert d["local_frame"]["crs"] == "EPSG:32632"
    assert {p["detected"]: p["surveyed"] for p in d["pairs"]} == {str(i): f"M{j}" for i, j in prob.true_pairing().items()}


def test_duplicate_surveyed_point_makes_its_pairing_ambiguous_only_when_used():
    rng = np.random.default_rng(23)
    prob = simulate_detections(site(rng, 20), rng, n_seen=15, n_false=3)
    used = int(prob.labels[prob.labels >= 0][0])
    unseen = int(np.setdiff1d(np.arange(20), prob.labels)[0])
    r = register_points(prob.detected, np.vstack([prob.surveyed, prob.surveyed[used]]), rng=rng)
    assert r.status == "ambiguous" and f"{used}/20" in r.reason and len(r.pairs) == 15
    r = register_points(prob.detected, np.vstack([prob.surveyed, prob.surveyed[unseen]]), rng=rng)
    assert r.status == "ok" and r.pairing() == prob.true_pairing()
