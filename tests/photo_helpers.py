"""Generated photos for tests: the JPEG bytes `cpdetect synth images` writes, as a file or decoded."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def generated_jpeg(index: int, seed: int, **options) -> tuple[bytes, list]:
    """The JPEG bytes of image ``index`` of the set ``cpdetect synth images --seed SEED`` makes with
    SynthImageOptions(**options), and its true markers."""
    from cpdetect.backgrounds import BackgroundLibrary, list_backgrounds
    from cpdetect.synth_images import SynthImageOptions, _encode, generate_image

    opt = SynthImageOptions(**options)
    sample = generate_image(index, seed, opt, BackgroundLibrary(list_backgrounds(opt.split)))
    return _encode(sample.image, "jpg", sample.jpeg_quality), sample.markers


def write_generated_jpeg(path: Path, index: int, seed: int, **options):
    """Write :func:`generated_jpeg` to ``path``; returns its true markers."""
    jpeg, markers = generated_jpeg(index, seed, **options)
    Path(path).write_bytes(jpeg)
    return markers


def generated_photo(index: int, seed: int, split: str = "train"):
    """Image ``index`` of the set ``cpdetect synth images --seed SEED --split SPLIT`` writes (decoded
    from the same JPEG bytes, BGR) and its true markers."""
    jpeg, markers = generated_jpeg(index, seed, split=split)
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR), markers
