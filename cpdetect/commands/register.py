"""``cpdetect register``: pair detected marker points with surveyed points, without IDs, and fit
``world_from_model`` (a 7-parameter similarity). See docs/formats.md "Registration JSON".

Exit codes: 0 ok; 3 ambiguous or failed (the JSON is still written, with the reason and alternatives);
2 bad input (one-line error naming the file and line).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from ..errors import InputError, UsageError
from ..fileio import write_json_atomic
from .args import seed_arg

log = logging.getLogger(__name__)

FORMAT = "cpdetect.registration/1"


def register(sub) -> None:
    p = sub.add_parser("register", help="pair detected marker points with surveyed points and fit world_from_model",
                       description="Pair detected marker points (model frame, any scale) with surveyed points "
                                   "without IDs and fit the similarity world_from_model. Exit 0: ok; 3: "
                                   "ambiguous or failed (JSON still written); 2: bad input.")
    p.add_argument("--detected", required=True, help="CSV id,x,y,z of detected marker points (model frame)")
    p.add_argument("--surveyed", required=True,
                   help="surveyed points: CSV name,x,y,z; an ODM gcp_list.txt (its header gives the CRS); "
                        "or Metashape markers .xml (chunk CRS)")
    p.add_argument("--crs", help="CRS of the surveyed coordinates, e.g. EPSG:32632 (fit in a local ENU frame)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="inlier distance in metres (default: 6 x --noise, adapted to the residuals)")
    p.add_argument("--noise", type=float, default=0.01,
                   help="expected per-axis noise of the points after scaling, metres (default 0.01)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed (probe selection)")
    p.add_argument("--out", required=True, help="registration JSON to write")
    p.set_defaults(func=run)


def _read_surveyed(path: Path, crs_text: str | None):
    """(names, (n, 3) float64 coordinates, pyproj CRS or None)."""
    from geometry.crs import CRSInputError, crs_from_user

    crs = None
    if crs_text is not None:
        try:
            crs = crs_from_user(crs_text)
        except CRSInputError as exc:
            raise UsageError(f"--crs: {exc}") from None
    if path.suffix.lower() == ".txt":
        try:
            from ..formats.odm import gcp_survey_points, read_gcp_list
        except ModuleNotFoundError:  # pragma: no cover - the ODM reader ships with cpdetect
            raise InputError("reading ODM gcp_list.txt files is not available in this version", path) from None
        gcps = read_gcp_list(path)
        pts = gcp_survey_points(gcps)
        if crs is not None and gcps.crs is not None and not crs.equals(gcps.crs):
            raise UsageError(f"--crs {crs_text} disagrees with the CRS in the header of {path} ({gcps.header})")
        return list(pts), np.array(list(pts.values()), dtype=np.float64).reshape(-1, 3), crs or gcps.crs
    if path.suffix.lower() == ".xml":
        from ..formats.metashape import read_metashape_markers

        markers = read_metashape_markers(path)
        pts = markers.survey_points()
        file_crs = None
        wkt = (markers.crs_wkt or "").strip()
        if wkt and not wkt.upper().startswith("LOCAL_CS"):
            try:
                file_crs = crs_from_user(wkt)
            except CRSInputError as exc:
                raise InputError(f"chunk CRS: {exc}", path) from None
        if crs is not None and file_crs is not None and not crs.equals(file_crs):
            raise UsageError(f"--crs {crs_text} disagrees with the chunk CRS of {path} ({file_crs.name})")
        return list(pts), np.array(list(pts.values()), dtype=np.float64).reshape(-1, 3), crs or file_crs
    from ..formats.points_csv import read_points_csv

    table = read_points_csv(path, min_points=3, what="surveyed points")
    return table.names, table.xyz, crs


def _sim_dict(sim) -> dict:
    return {"scale": sim.scale, "rotation": sim.R.tolist(), "translation": sim.t.tolist(),
            "matrix": sim.matrix.tolist()}


def _num(x: float):
    return None if x is None or not math.isfinite(x) else float(x)


def run(args) -> int:
    from geometry.crs import CRSInputError, LocalFrame
    from geometry.registration import RegistrationConfig, register_points
    from geometry.transforms import Sim3

    from ..formats.points_csv import read_points_csv

    for opt in ("tolerance", "noise"):
        v = getattr(args, opt)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise UsageError(f"--{opt} must be a positive number of metres, got {v}")
    det = read_points_csv(args.detected, min_points=3, what="detected points")
    names, xyz, crs = _read_surveyed(Path(args.surveyed), args.crs)
    if len(names) < 3:
        raise InputError(f"need at least 3 surveyed points, found {len(names)}", args.surveyed)
    try:
        frame = LocalFrame.from_points(xyz, crs)
        local = frame.to_local(xyz)
    except CRSInputError as exc:
        raise InputError(str(exc), args.surveyed) from None

    config = RegistrationConfig(tolerance=args.tolerance, noise=args.noise)
    result = register_points(det.xyz, local, rng=np.random.default_rng(args.seed), config=config)

    # "world" is the surveyed coordinates themselves for plain Cartesian input (offset added back),
    # and the local ENU frame described by "local_frame" when a CRS is given.
    to_world = Sim3(1.0, np.eye(3), frame.origin) if frame.kind == "offset" else Sim3.identity()

    def world_sim(sim):
        return to_world @ sim

    doc = {
        "format": FORMAT,
        "status": result.status,
        "reason": result.reason,
        "world": "surveyed" if frame.kind == "offset" else "local_frame",
        "scale": None, "rotation": None, "translation": None, "matrix": None,
    }
    if result.world_from_model is not None:
        doc.update(_sim_dict(world_sim(result.world_from_model)))
    doc.update({
        "pairs": [{"detected": det.names[p.detected], "surveyed": names[p.surveyed], "residual_m": p.residual}
                  for p in result.pairs],
        "unmatched_detected": [det.names[i] for i in result.unmatched_detected],
        "unmatched_surveyed": [names[i] for i in result.unmatched_surveyed],
        "rms_m": _num(result.rms_m),
        "sigma_m": _num(result.sigma_m),
        "tolerance_m": _num(result.tolerance_m),
        "hypotheses_tried": result.hypotheses_tried,
        "alternatives": [
            {"pairs": [{"detected": det.names[d], "surveyed": names[s]} for d, s in a.pairs],
             "rms_m": a.rms, "n_pairs": a.n_inliers, **_sim_dict(world_sim(a.world_from_model))}
            for a in result.alternatives],
        "detected_file": str(args.detected),
        "surveyed_file": str(args.surveyed),
    })
    if frame.kind == "enu":
        doc["local_frame"] = frame.to_dict()
    write_json_atomic(args.out, doc)
    msg = (f"{result.status}: {len(result.pairs)} pairs, rms {result.rms_m * 1e3:.1f} mm"
           if result.world_from_model is not None else f"{result.status}")
    if result.reason:
        msg += f" ({result.reason})"
    # a failed or ambiguous registration is said even with --quiet: the exit code alone does not say why
    (log.info if result.status == "ok" else log.warning)("%s -> %s", msg, args.out)
    return 0 if result.status == "ok" else 3
