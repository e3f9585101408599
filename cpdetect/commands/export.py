"""``cpdetect export-onnx MODELDIR OUT.onnx``: export the learned model for torch-free inference."""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("export-onnx", help="export a trained hma model to ONNX (OpenCV DNN inference)",
                       description="Write the network's single-scale trunk (class logits + attention) as "
                                   "ONNX with dynamic height and width. The 'hma' detector uses it through "
                                   "cv2.dnn when PyTorch is not installed: put it in the model folder as "
                                   "model.onnx. The export is checked against PyTorch at two input sizes.")
    p.add_argument("model_dir", metavar="MODELDIR", help="model folder (config.json + model.pt)")
    p.add_argument("out", metavar="OUT.onnx", help="ONNX file to write")
    p.add_argument("--no-check", action="store_true", help="skip the OpenCV-vs-PyTorch comparison")
    p.add_argument("--tolerance", type=float, default=1e-3,
                   help="largest allowed probability difference in the check (default 1e-3)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import CpdetectError, UsageError

    try:
        from learned.export import export_onnx
        from learned.hma import load_model
    except ModuleNotFoundError as exc:
        if exc.name in ("torch", "onnx"):
            raise UsageError(f"'cpdetect export-onnx' needs {exc.name}: pip install 'cpdetect[learned]'") from None
        raise
    if not args.tolerance > 0 or args.tolerance == float("inf"):  # checked before anything is written
        raise UsageError(f"--tolerance must be a positive number, got {args.tolerance}")
    model = load_model(args.model_dir)
    path = export_onnx(model, args.out)
    log.info("wrote %s", path)
    if args.no_check:
        return 0
    from learned.export import check_parity

    worst = check_parity(model, path)
    log.info("OpenCV DNN vs PyTorch: largest P(marker) difference %.2e", worst)
    if not worst <= args.tolerance:
        raise CpdetectError(f"OpenCV and PyTorch differ by {worst:.2e} > {args.tolerance:g} in P(marker)",
                            path, exit_code=1)
    return 0
