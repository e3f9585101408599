"""Generated photos for tests that need the detector's file path (a JPEG as `cpdetect synth images` writes it)."""
from __future__ import annotations

from pathlib import Path


def write_generated_jpeg(path: Path, index: int, seed: int, **options):
    """Write image ``index`` of the set ``cpdetect synth images --seed SEED`` makes with
    SynthImageOptions(**options) to ``path`` (the same JPEG bytes); returns its true markers."""
    from cpdetect.backgrounds import BackgroundLibrary, list_backgrounds
    from cpdetect.synth_images import SynthImageOptions, _encode, generate_image

    opt = SynthImageOptions(**options)
    sample = generate_image(index, seed, opt, BackgroundLibrary(list_backgrounds(opt.split)))
    Path(path).write_bytes(_encode(sample.image, "jpg", sample.jpeg_quality))
    return sample.markers
