"""``cpdetect demo``: a self-contained run on synthetic data.

For now it generates a small synthetic marker image set and evaluates every registered detector that
can be built on it (a detector whose code or weights are missing is skipped with a one-line note).
Later stages (scene synthesis, registration, georeferencing) are added as further steps here.
"""
from __future__ import annotations

import logging
from pathlib import Path

from .args import seed_arg

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("demo", help="run cpdetect end to end on synthetic data",
                       description="Generate a small synthetic marker image set and evaluate the "
                                   "registered detectors on it.")
    p.add_argument("--workdir", default="cpdetect-demo", help="folder for all demo outputs (default ./cpdetect-demo)")
    p.add_argument("--n", type=int, default=12, help="synthetic images to generate (default 12)")
    p.add_argument("--seed", type=seed_arg, default=0, help="random seed (default 0)")
    p.add_argument("--detectors", nargs="*", metavar="NAME",
                   help="detectors to evaluate (default: every registered one)")
    p.add_argument("--no-georef", action="store_true",
                   help="skip the georeferencing run on a synthetic site")
    p.add_argument("--site-images", type=int, default=32,
                   help="photos of the synthetic site for the georeferencing run (default 32)")
    p.set_defaults(func=run)


def make_images(workdir: Path, n: int, seed: int) -> Path:
    """Step 1: a synthetic marker image set in ``workdir/images-set``; returns the dataset folder."""
    from ..synth_images import SynthImageOptions, write_synth_images

    out = workdir / "images-set"
    write_synth_images(out, n, seed, SynthImageOptions())
    log.info("demo: %d synthetic images in %s", n, out)
    return out


def build_detector(name: str):
    """The detector ``name`` with default settings, or (None, reason) when it cannot be built."""
    from ..detector import get_detector

    try:
        return get_detector(name), None
    except ModuleNotFoundError as exc:
        return None, f"not available (module {exc.name!r} not installed or not written yet)"
    except Exception as exc:  # a broken or weightless detector must not stop the demo
        return None, f"cannot be built: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"


def evaluate_detectors(dataset_dir: Path, names: list[str], workdir: Path) -> dict[str, dict | str]:
    """Step 2: evaluate each detector; returns name -> metrics dict, or name -> reason it was skipped.
    Each detector's metrics are written to ``workdir/metrics-<name>.json``."""
    from ..dataset import load_dataset
    from ..errors import CpdetectError
    from ..evaluate import evaluate
    from ..fileio import write_json_atomic

    dataset = load_dataset(dataset_dir)
    results: dict[str, dict | str] = {}
    for name in names:
        det, reason = build_detector(name)
        if det is None:
            results[name] = reason or "cannot be built"
            continue
        try:
            metrics = evaluate(dataset, det)
        except CpdetectError:
            raise  # the data, not the detector: report it
        except Exception as exc:  # a detector that crashes must not stop the demo
            first = str(exc).splitlines()[0] if str(exc) else ""
            results[name] = f"failed while detecting: {type(exc).__name__}: {first}"
            continue
        metrics["detector"] = name
        write_json_atomic(workdir / f"metrics-{name}.json", metrics)
        results[name] = metrics
    return results


def summary_lines(results: dict[str, dict | str]) -> list[str]:
    """One line per detector: the headline metrics, or why it was skipped."""
    def f(v):
        return "n/a" if v is None else f"{v:.3f}"

    lines = []
    for name, r in results.items():
        if isinstance(r, str):
            lines.append(f"{name:12s} skipped: {r}")
            continue
        px = r.get("pixel") or {}
        lines.append(f"{name:12s} precision {f(r['precision'])}  recall {f(r['recall'])}  f1 {f(r['f1'])}  "
                     f"centre error {f(r['centre_error_px']['mean'])} px  pixel AP {f(px.get('ap'))}  "
                     f"{f(r['seconds_per_megapixel'])} s/MP")
    return lines


def run(args) -> int:
    from ..detector import available_detectors
    from ..errors import UsageError

    if args.n < 1:
        raise UsageError("--n must be >= 1")
    workdir = Path(args.workdir)
    names = args.detectors if args.detectors else available_detectors()
    dataset_dir = make_images(workdir, args.n, args.seed)
    results = evaluate_detectors(dataset_dir, names, workdir)
    print(f"synthetic images: {dataset_dir} ({args.n} images, seed {args.seed})")
    for line in summary_lines(results):
        print(line)
    evaluated = [n for n, r in results.items() if not isinstance(r, str)]
    files = ", ".join(str(workdir / f"metrics-{n}.json") for n in evaluated)
    print(f"metrics: {files or 'none (no detector could be built)'}")
    if getattr(args, "no_georef", False):
        return 0
    if "classical" not in names:
        print("georef on a synthetic site: skipped (it runs the classical detector, which --detectors leaves out)")
        return 0
    cmp = run_georef_step(workdir, args.seed, getattr(args, "site_images", 32))
    return 0 if cmp["all_paired"] else 1


def run_georef_step(workdir: Path, seed: int, n_images: int) -> dict:
    """Step 3: a synthetic site, ``georef`` on it with the default detector, checked against the truth
    (see :mod:`cpdetect.georef_demo`)."""
    from ..georef_demo import run_site_demo

    return run_site_demo(workdir, seed=seed, detector="classical", n_images=n_images)
