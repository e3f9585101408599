"""The training data of the fitting scripts in bench/: generated images with *train*-split backgrounds
only, so that nothing fitted ever sees a test-split background."""
from __future__ import annotations

import tempfile
from pathlib import Path


def train_split_dataset(data: str | None, n: int, seed: int, prefix: str):
    """The dataset at ``data`` (generated there with ``n`` images of ``seed`` when it has none yet;
    a temporary folder when ``data`` is None). Raises SystemExit(2) with a message when any of its
    images has backgrounds of another split."""
    import sys

    from cpdetect.dataset import load_dataset
    from cpdetect.synth_images import SynthImageOptions, write_synth_images

    root = Path(data) if data else Path(tempfile.mkdtemp(prefix=prefix))
    if not (root / "markers.json").exists():
        write_synth_images(root, n, seed, SynthImageOptions(split="train"), workers=2)
    ds = load_dataset(root)
    other = {im.meta.get("split") for im in ds.images} - {None, "train"}
    if other:
        print(f"{root}: refusing to fit on backgrounds of split(s) {sorted(other)}: train only", file=sys.stderr)
        raise SystemExit(2)
    return ds
