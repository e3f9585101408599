"""The learned detector ``hma``: HMA probability map -> marker instances with refined centres.

Steps for one image (uint8 gray or BGR; a path is read as gray):

1. P(marker) by :func:`learned.infer.probability_map` (downscale to ``max_side``, tiles, N-scale HMA),
   through OpenCV DNN or torch (``backend``; "auto" = OpenCV on model.onnx on the CPU, else torch);
2. instances: connected components of P >= ``threshold`` larger than ``min_radius_px``;
3. centre: seeds on the full-resolution image (the probability-weighted centroid and the strongest
   X-corners on the component, :func:`cpdetect.xcorner.xcorner_seeds`), each refined with
   :func:`cpdetect.refine.refine_center_coarse_to_fine` (``refine``; "none" skips it); the first
   refined centre where the classical marker model fits (:func:`cpdetect.classical.verify_marker_at`)
   wins, else the centroid's refinement when sharp. On the test split this took instance recall from
   0.795 to 0.850 and the mean centre error from 0.121 to 0.075 px (the centroid is a poor seed under perspective,
   occlusion and at the image border). With ``classical_seeds`` the classical detector's markers on
   the component are tried first, and a blob whose centre one of them confirms is kept (a fresh
   300-image test-split set: instance F1 0.928 -> 0.934; opt-in); ``large_classical_seeds`` gives
   them on images the network sees downscaled only (the default since stop 65, with only the
   classical markers scored 0.99 or more, ``classical_seed_min_score``), and with ``classical_centres``
   a blob on which one lies takes its centre where the blob's own choice disagrees (opt-in). With a
   centre ranker beside the weights
   (``centre_rank.json``, :mod:`learned.centre_choice`) every seed (up to ``rank_seeds``, the most
   point-symmetric of the ``seed_pool`` strongest X-corners) is refined instead, and the candidate
   it scores highest from the refinement's evidence and the symmetry of the image and the blob
   about it wins;
   Blobs that yield no marker, and that the network is not sure of (mean P < ``clear_rejected_below``),
   are cleared from the probability map the detector returns: louvers, window crosses, dark arches
   (and, on images seen downscaled, sure ones of one grey tone: ``large_clear_flat_below``);
   on images seen at ``small_scales`` (by default), that map is the mean with the mirror image's
   (``mirror_map``, :mod:`learned.mirror_map`);
4. keep or drop: with an instance model beside the weights (``instance_score.json``, see
   :mod:`learned.instances`), a logistic model over the blob's confidence, shape and centre evidence
   decides, and its probability is the detection's score; without one, rules do (a verified centre,
   or a sharp one at the centroid, kept; score = mean P);
5. type: from the marker model's outline fit at that centre (``type_by`` "model"); otherwise, or when
   the model does not fit, by shape: ellipse vs quadrilateral fit of the upsampled component outline
   (circle vs square sheet), then for quadrilaterals the phase of the checker's dark/bright
   boundaries relative to the outline edges (square: parallel to the edges; diagonal: through the
   corners). Type accuracy on the test split: 0.92 by model, 0.67 by shape alone.

This module imports torch only through the torch backend, so the detector runs where torch is not
installed (OpenCV backend on the shipped model.onnx).
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cpdetect.centre_reach import CENTRE_REACH_MIN, centre_reach
from cpdetect.classical import TAG_FIELD
from cpdetect.detector import as_gray_uint8, settings_from_dataclass
from cpdetect.refine import METHODS, refine_in_outline
from cpdetect.types import DetectionResult, MarkerDetection

from .blob_tone import interior_spread
from .centre_choice import CentreRanker, load_centre_ranker
from .instances import InstanceModel, blob_features, load_instance_model
from .lower_map import corrected_by_lower
from .mirror_map import keep_blobs_of, mirrored_mean

DEFAULT_MODEL_DIR = Path(__file__).resolve().parent / "weights" / "default"
# the networks shipped as package data, by the name the setting ``network`` takes
SHIPPED_NETWORKS = {"default": DEFAULT_MODEL_DIR, "lite": DEFAULT_MODEL_DIR.parent / "lite"}
# the classical marker score (package data of cpdetect) whose values the shipped centre ranker and
# instance model were fitted on (those trees of 2026-11-25); the classical detector's own were
# refitted since on more images, and a model keeps the inputs it was fitted with
MODEL_SCORE_FILE = "marker_score_hma.json"
# where the classical scan leaves a candidate it has judged not to be a marker (its trace's stages):
# a tag's bit cells around it, a centre grey unlike an X-corner's, a low marker score, another corner
# of the same checker beside it (``large_classical_veto``)
CLASSICAL_VETO_STAGES = ("verify: " + TAG_FIELD, "centre grey", "score", "single saddle")


def default_model_dir(network: str = "default", setting: str = "network") -> Path:
    """The folder of a shipped network (config.json, model.pt and/or model.onnx): "default" or
    "lite" (:data:`SHIPPED_NETWORKS`); another name is refused, the error naming ``setting``."""
    if network not in SHIPPED_NETWORKS:
        raise ValueError(f"{setting} must be one of {', '.join(SHIPPED_NETWORKS)}, got {network!r}")
    return SHIPPED_NETWORKS[network]


def shipped_weights_present(network: str = "default") -> bool:
    d = default_model_dir(network)
    return (d / "config.json").exists() and ((d / "model.pt").exists() or (d / "model.onnx").exists())


def _shipped_folder(network: str) -> Path:
    """:func:`default_model_dir`, refused with a one-line UsageError when its weights are missing."""
    if not shipped_weights_present(network):
        from cpdetect.errors import UsageError

        raise UsageError(f"the shipped hma weights are missing ({default_model_dir(network)}); "
                         "pass model_dir=... (a folder written by 'cpdetect train')")
    return default_model_dir(network)


# a classical marker under the seeds' score cut confirms a seed-kind centre only this close to it (image
# pixels): both come from cpdetect.refine.refine_center on the same pixels (large_seed_confirm_min_score)
SEED_CONFIRM_PX = 1.5
MAX_SCALE = 4.0  # the largest inference scale: twice the paper's largest (2.0)


@dataclass(frozen=True)
class HMASettings:
    """Settings of the ``hma`` detector.

    model_dir: model folder (None = the shipped network named by ``network``). network: which shipped
    network: "default" (w16_tiny) or "lite" (w16_lite, stop 52: the OCR head narrowed, 0.72x the time
    per image; on fresh test-split seeds 11000 / 11100, with ``rank_seeds_unsure=1``, instance F1
    0.964 / 0.960, pixel IoU 0.916 / 0.935, centre 0.067 / 0.074 px mean, where the default gave
    0.961 / 0.962, 0.916 / 0.943, 0.062 / 0.065; not the default: it failed the rule written for that
    on 11100's pixel IoU and centre; learned/weights/default/TRAINING.md). large_network: the
    shipped network for an image the network sees downscaled (longest side over ``max_side``, e.g.
    a 45 MP photograph), None = ``network`` for every image; ignored with ``model_dir`` (a folder of
    the user's goes to every image); the instance model and centre ranker stay those of ``network``.
    ``large_network=lite`` (stop 55, opt-in) took 26-31 % off the time of two fresh 45 MP sets but
    failed its rule on one of them (seed 12100: pixel IoU 0.834 against 0.878, a covered marker
    found 9 px off; TRAINING.md). scales: inference scales (must contain 1.0, each in (0, 4]),
    default (0.5, 1.0): two-scale HMA, as trained; (1.0,) is faster. small_scales: the scales for an
    image small enough that its largest pass fits in ``max_side`` (default (0.5, 1.0, 1.5, 2.0), so up
    to 1024 px for the default max_side; None = always ``scales``): the 2.0 pass shows the network
    small markers at twice their size. On the validation set (0.5, 1.0, 2.0) found 107 of 123 markers
    instead of 102, with 2 false instead of 4, at about 5x the time per megapixel; the 1.5 pass added
    on 2026-11-26 found 15 more of the 3,790 markers of six 300-image sets (two train-split dev sets,
    four fresh test-split ones) for 3 more false ones and raised pixel IoU by 0.001-0.005 on each,
    at 1.4x the time (5.1 against 3.6 s per megapixel); see TRAINING.md. backend: "auto" (OpenCV on the
    exported model.onnx when the device is the CPU: faster there than torch, see
    :mod:`learned.infer`; else torch), "torch" or "opencv". device: torch device.
    threshold: P(marker) cut for instances. max_side: the longest side the network sees (pixels; the
    image is downscaled to it; None = full resolution). tile / overlap: tiling of the processing image
    (pixels) for bounded memory. min_radius_px: smallest instance kept (equal-area radius, image
    pixels). refine: centre refinement method of cpdetect.refine ("auto", "symmetry", "saddle",
    "hough", "model") or "none". drop_unrefined: drop instances where refinement finds no X-corner
    (blobs of texture are not markers). max_sigma_px: drop instances whose refined centre is less
    certain than this (image pixels): on the validation set (train-split backgrounds) 0.3 took false markers from
    17 to 4 for 5 of 89 true ones, most of them mislocated onto another corner. max_sigma_verified_px:
    the same bound for a centre where the classical marker model fits (an occluder's edge in the
    refinement window inflates sigma; the model guards against a wrong corner): 0.6 found one more
    of 123 validation markers, no false one. clear_rejected_below: a blob that yields no marker is
    cleared from the probability map unless its mean P is at least this (0 keeps the network's map
    as it is); 0.9 raised pixel IoU from 0.890 to 0.893 on validation and from 0.859 to 0.872 on a
    fresh test-split set (seed 777), with no blob of a found marker touched.
    large_clear_rejected_below: the same cut for the images the network sees downscaled (longest side
    over ``max_side``; None: ``clear_rejected_below``). On 45 MP images many of the blobs the network is
    sure of that yield no marker hold none (tag bits, a dark splotch, an occluder's edge), but 0.97 did not
    become the default by two rules written first (stop 58): on four fresh 45 MP sets pixel IoU stayed the
    same on two, rose on one (0.927 -> 0.967) and fell on one (0.867 -> 0.865, a covered marker's blob
    cleared), the markers the same; learned/weights/default/TRAINING.md.
    large_drop_unverified_seeds: on the images the network sees downscaled, drop an instance whose
    centre is a refined X-corner seed that neither the marker model nor a classical marker confirms
    (kind "seed"); on nine seen 45 MP sets such centres were 9 false markers (checkerboard and shadow
    corners) and 2 true ones. The default since stop 58, by a rule written before its test sets existed:
    on fresh 45 MP sets 15000 / 15100, 7 -> 4 false markers for 1 true one, instance F1 0.905 / 0.971 ->
    0.916 / 0.980. Images up to ``max_side`` are not touched. large_clear_unverified_seeds: on the
    images the network sees downscaled, clear the blob of such a rejected seed-kind centre from the
    returned map whatever its mean P (``clear_rejected_below`` keeps the blobs the network is sure of;
    on twelve seen 45 MP sets those with seed-kind centres held about 467,000 false map pixels,
    checkerboard corners of radius 680-890 px among them, against 55,000 true ones). Markers found do
    not change. The default since stop 59, by a rule written before its test sets existed: on six
    fresh 45 MP sets (15200-15700) pixel IoU 0.808 / 0.848 / 0.882 / 0.815 / 0.829 / 0.771 -> 0.948 /
    0.857 / 0.960 / 0.822 / 0.845 / 0.763 (mean 0.825 -> 0.866), the same markers.
    large_classical_veto: on the images the network sees downscaled, also run the classical
    detector (with its trace) and drop a marker, clearing its blob from the map, where the classical
    detector kept none within half its radius and one of its candidates within max(8 px, 0.1 radius)
    of the centre stopped at a test that says "not a marker" (:data:`CLASSICAL_VETO_STAGES`: a tag's
    dark field, the centre's grey, the score, the single saddle); on twelve seen 45 MP sets that would
    have dropped 10 of hma's 14 false markers (tag bit-cell and checkerboard corners) and none of its
    526 true ones. The default since stop 59, by a rule written before its test sets existed: on six
    fresh 45 MP sets (15800-16300) false markers 11 -> 3, the same 294 true ones, instance F1 higher on
    five and the same on one, mean pixel IoU 0.841 -> 0.896; the classical scan adds about 0.3 s per
    45 MP image. Not for the images the network sees whole: on four seen 640 x 480 sets it would have
    dropped 52 true markers for 8 false ones (hma finds many markers there that the classical score
    turns down). large_classical_seeds: on the images the network sees downscaled, the classical
    detector's markers (from the run the veto makes anyway, or a run of their own) serve as seeds, as
    ``classical_seeds`` gives them on every image: a centre one of them confirms is kept, and its blob
    stays in the map, whatever ``large_drop_unverified_seeds`` / ``large_clear_unverified_seeds`` and
    the instance model say of a seed nothing confirmed. On seen 45 MP sets those two rules had dropped
    markers partly out of frame (radius 835 px on 15800, 384 px on 15700) whose centre the classical
    detector had found. classical_centres: wherever classical markers are given as seeds (either
    setting above), a blob on which one lies (at its map pixel) and whose chosen centre none of them
    confirms takes the best-ranked of its centre options one confirms, else that classical marker's
    own centre, type and score (:func:`_classical_centre`): on seen 45 MP set 15500 a marker of radius
    841 px centred 15 px from the frame's edge, found by the classical detector 0.03 px off, whose
    blob's refinement (a window of the blob's radius, running off the image) gave only the centroid
    490 px off. Both opt-in (stop 60). large_classical_seeds alone failed its rule on fresh 16600-17100
    (278 -> 280 found, 3 -> 4 false, mean IoU 0.8812 -> 0.8773: a tag's bit-cell corner the classical
    detector kept confirmed hma's blob there, 17100's IoU -0.024). Both together passed a second rule
    on fresh 17200-17700 (282 -> 284 found, 6 -> 6 false, mean IoU 0.8885 -> 0.8905) but on 16600-17100
    gave 278 -> 280 found, 3 -> 5 false, mean IoU 0.8812 -> 0.8549: on 17000 (0.924 -> 0.790) a
    classical false marker on a large checkerboard's corner became the centre of the network's blob
    over the board. Over all twelve sets they lower mean IoU (0.8849 -> 0.8727), so they stayed opt-in;
    learned/weights/default/TRAINING.md. classical_seed_min_score: only the classical markers scored at
    least this serve as seeds (either setting above, and so for ``classical_centres``); 0 takes them all
    (as stop 60 did). On 17000 / 17100, regenerated from their seeds in stop 65, and on 34400 the
    classical false markers scored 0.68-0.975 and 138 of the 150 true ones 0.99 or more. With 0.99,
    large_classical_seeds is the default since stop 65, by a rule written before its fresh sets
    existed (rule 21): on fresh 45 MP sets 34600-35100, 280 -> 283 markers found, no false one either
    way, mean pixel IoU 0.9017 -> 0.9238 (34600 0.802 -> 0.891, a marker of radius 683 px kept), no
    set lower, the markers found by both at the same centres. large_seed_confirm_min_score: on the
    images the network sees downscaled, a classical marker scored at least this (and under
    ``classical_seed_min_score``) within ``SEED_CONFIRM_PX`` of a blob's seed-kind centre confirms it,
    so that ``large_drop_unverified_seeds`` / ``large_clear_unverified_seeds`` spare it; it seeds
    nothing and overrides neither the instance model nor any centre (None: off). Opt-in (stop 67):
    at 0.95, on seen 45 MP set 36100 it keeps a square of radius 400 px whose seed centre is 0.007 px
    off, confirmed at score 0.968 (pixel IoU 0.903 -> 0.938), but on regenerated 17100 a tag's
    bit-cell corner the classical detector keeps at 0.975 (IoU 0.895 -> 0.861, one false marker more),
    so rule 25 stopped at its seen check; learned/weights/default/TRAINING.md.
    large_clear_flat_below: on the images the
    network sees downscaled, a blob that yields no marker is also cleared from the map, however sure
    the network is of it, when its inside shows one grey tone: :func:`learned.blob_tone.interior_spread` under
    this many grey levels (0 is off). On 36 seen 45 MP sets the blobs that stay in the map without a
    marker held 544,518 false map pixels and 380,975 true ones; those under 3 levels (plain panels,
    dark splotches) about 250,000 false and 15,961 true (covered markers of which one dark sector
    shows), and no kept marker's blob was under 19.9. The default (3.0) since stop 61, by a rule
    written before its test sets existed: on six fresh 45 MP sets (18000-18500) the same 295 true and
    0 false markers, pixel IoU 0.863 / 0.842 / 0.897 / 0.835 / 0.943 / 0.827 -> 0.918 / 0.920 / 0.896 /
    0.852 / 0.943 / 0.866 (mean 0.868 -> 0.899); learned/weights/default/TRAINING.md. Markers found
    never change. large_spare_reach: on the images the network sees downscaled, a centre whose
    four-sector pattern reaches into the centre at least this strongly (:func:`cpdetect.centre_reach.
    centre_reach`, the X-corner's strength on a small ring around it against the ring of half the
    blob's radius) keeps the marker that ``large_drop_unverified_seeds`` or ``large_classical_veto``
    would drop (None: off). Uncovered, a marker gives 0.55-1 (blur lowers it); an occluder that
    crosses the ring of half the blob's radius weakens the X-corner there and not near the centre,
    and lifts it over 1. On 36 seen 45 MP sets (stops 59-61), of the centres those two rules alone
    dropped, the seed-only ones at 1.0 or more were 11 true markers (most of them covered) and no false
    one (the false ones reached 0.98 at most), the vetoed ones 6 true and 4 false (1.04-1.08: corners
    of large checkerboards, point-symmetric about their centre, sym180 0.96-1.0, where the true ones
    had 0.36-0.97). So a centre is spared only where its sym180 (the image's and the blob's
    correlation with their half-turn about it, :mod:`learned.centre_choice`) is also under
    ``large_spare_max_sym180``: a cover breaks a marker's point symmetry, a checkerboard keeps it
    (without a centre ranker sym180 is not measured, 0, and only the reach decides).
    Opt-in (stop 62): reach 1.0 alone failed its rule on fresh 45 MP sets 19600-20100 (284 -> 290
    found, 3 -> 4 false, mean IoU 0.8025 -> 0.8174, but 20000 0.758 -> 0.731: a checkerboard corner);
    with the gate at 0.9 it failed on fresh 20200-20700 (293 -> 297 found, 1 -> 2 false, mean IoU
    0.9183 -> 0.8875: a checkerboard cut by the image edge, sym180 0.82, spared on 20500, 0.903 ->
    0.697); learned/weights/default/TRAINING.md.
    large_lower_scale: on the images the network sees downscaled, one more network pass at this
    scale (0.25 by default), fused below ``scales`` by the same attention, corrects the map the
    detector returns (:mod:`learned.lower_map`): a kept marker's blob takes that map's extent where
    it is higher (a large marker's inside, which the 2048-pixel passes leave partly under 0.5), and a
    blob that yields no marker is cleared where that map does not confirm it. Markers found never
    change. None, or a scale not under every one of ``scales``: no such pass. The default since stop
    63, by a rule written before its fresh 45 MP sets existed (32000-32500): mean pixel IoU 0.9335 ->
    0.9428, no set lower by more than 0.0043, the same markers, 4.7 % more time. On the sets of the
    rule before (31000-31500) it had failed: two sets fell by 0.012 / 0.008, each by a false marker's
    blob grown, both bowtie shadows the generator no longer draws; learned/weights/default/TRAINING.md.
    max_seeds: X-corner
    seeds tried per instance besides the centroid (0 = centroid only). type_by: "model" (the
    classical outline fit at the centre, falling back to shape) or "shape". threads: CPU
    threads of the network (None, the default: 1 for torch, OpenCV's own setting, all cores, for
    OpenCV; see below).
    instance_model: "auto" (decide keep or drop with the instance model stored beside the weights,
    :mod:`learned.instances`, when there is one) or "none" (the rules above). instance_threshold:
    its cut on P(marker) (None = the one stored with it). max_sigma_seed_px: with an instance model,
    a blob where no centre is verified or sharp still gets its best refined centre up to this
    uncertainty, and the model decides. min_blob_mean_p: with an instance model, a blob whose mean P
    is below this is dropped without refining its seeds: on 500 train-split images (fit11, dev505)
    the model scored none of the 145 such blobs at 0.6 above 0.09 (its cut: 0.46), and they held
    no marker it kept; skipping them took the instance stage of the textured 45 MP bench image
    from 3.1 to 2.7 s (9 texture blobs of 23) and 3 % off the refinement of the small images
    (0 = refine every blob).
    centre_ranker: "auto" (with an instance model and a centre ranker beside the weights,
    ``centre_rank.json``, :mod:`learned.centre_choice`: every seed is refined and the candidate the
    ranker scores highest is the blob's centre, instead of the first verified one) or "none".
    rank_seeds: X-corner seeds per blob besides the centroid when the ranker chooses (a partly
    covered marker's own centre is often not among the three strongest corners on its blob);
    ``rank_seeds_unsure`` of them on a blob whose mean P is under ``rank_sure_mean_p``: texture
    blobs, which get the most seeds refined for nothing (on the textured 45 MP bench image, 14 blobs
    of mean P 0.61-0.84 beside the markers' 0.97-0.99: their centres took 1.80 s with 8 seeds
    everywhere, 0.84 s with 3, against 0.80 s for the rules), while 10 of the 15 blobs of the
    train-split fitting data whose right centre came from a seed past the third had mean P >= 0.85.
    rank_stop: the seeds are refined in order (centroid, then the X-corners) and the
    search stops at the first candidate the ranker scores at least this (1 = refine them all).
    rank_stop_model: and whose classical marker-model score (:func:`cpdetect.classical.verify_marker_at`)
    is at least this. Beside an occluder the centroid's refinement can settle on the corner where
    the occluder's edge meets a sector edge, 2-3 px off, which the ranker may score over
    ``rank_stop`` while the marker model barely fits there (scores near 0.03 against 0.99 at a
    centre); a later X-corner seed then refines to the centre. At 0.5 against 0 (the rule before
    2026-11-27), on train-split sets: dev1111 the same 803 / 7 markers / false ones, centre mean
    0.0589 -> 0.0548 px (one marker 3.4 -> 0.13 px off); dev1212 801 / 15 -> 802 / 14 (a marker
    placed beyond the match tolerance, now 0.3 px off); the all-covered occ77 351 -> 352 found,
    centre mean 0.261 -> 0.248 px; dev808 / dev909 (the ranker's fitting sets) the same; the same
    time per image (``rank_stop`` 1 gave the same markers at 1.7 times the time on occ77).
    seed_pool: with the ranker, this many of the strongest X-corners of a blob are looked at, and
    those refined are the most point-symmetric of them (the image turned 180 degrees about the seed
    like itself, turned 90 like its negative: sym180 - sym90 of
    :func:`learned.centre_choice.point_symmetry`, cheap beside a refinement); 0 = the strongest
    ones. A low-contrast marker's centre is often weaker as an X-corner than the corners its
    outline makes with a bright background: in one dev909 image a square marker of radius 57 px
    and contrast 40 had its centre ninth among the blob's X-corners, after its outline's corners
    against the sky, and was lost. On the ranker's train-split fitting images (dev808 + dev909, 1,266
    markers) 24 took the markers found from 1,147 to 1,155 and the false ones from 19 to 18; on the
    fresh test-split sets seeds 9000 / 9100 / 9200, 561 / 586 / 581 found -> 561 / 587 / 583 and
    7 / 7 / 3 false -> 8 / 7 / 3 (the new false one a crossing of two grass paths the network
    holds for a marker). On the textured 45 MP bench image it costs 0.14 s (2.35 -> 2.49 s, same
    markers); applied to the blobs of mean P >= rank_sure_mean_p only it cost nothing there but
    found 1,150 of the 1,266 and on the test sets nothing more.
    unsure_min_symmetry: with the centre ranker, a blob whose mean P is under ``rank_sure_mean_p``
    gets no centre search at all (it is dropped, as under ``min_blob_mean_p``) when neither its
    centroid nor any seed of its pool has a sym180 - sym90 (:func:`_seed_symmetry`, 1.8 at a
    checker's centre) of at least this, measured before any refinement; None (``--set
    unsure_min_symmetry=null``) refines every such blob. A blob with a classical marker on it is
    always searched. On the train-split sets dev1111 (400 images) and dev1212 (200) and the textured
    45 MP bench image, the 24 blobs of mean P under 0.85 that the instance model kept had a best
    symmetry of 0.53 or more, the 93 it dropped from -0.35 up. Stop 53 shipped 0.2 (the largest tenth
    at least 0.3 under 0.53, by the rule written for it), which skips 33 of the 117: on the fresh
    test-split sets 11200 / 11300, generated after that rule was written, every figure of ``cpdetect
    eval`` was the same with it as without (557 / 7 and 576 / 7 markers found / false), and on the
    textured 45 MP bench JPEG it skipped 2 of the 8 texture blobs. Since stop 54 it is 0.5 (the largest
    tenth at most 0.53), which skips 65 of the 117 and 7 of the bench JPEG's 8, by a rule written before
    fresh seeds 11400 / 11500 existed: there too every figure and every image's found / false / missed
    count stayed the same against 0.2 (571 / 7 and 634 / 1 markers found / false). It only saves time,
    on textured photographs (the bench JPEG: see TRAINING.md).
    min_seed_symmetry: with the centre ranker, an X-corner seed of any blob (not the centroid, not a
    classical marker on the blob) whose sym180 - sym90 (:func:`_seed_symmetry`, before any
    refinement) is under this is not refined; None refines them all (the seeds are still the most
    point-symmetric ``rank_seeds`` of the ``seed_pool``). A seed with nothing point-symmetric about it
    is an outline's corner or texture, and on a large marker each refinement costs 40-300 ms. 0.0
    since stop 55: the largest tenth at most 0.019, the least symmetry of an X-corner seed whose
    refinement became a found marker's centre on 400 train-split images (dev1111 / dev1212, 63 such
    seeds, the next 0.31); there it skips 409 of 1,690 refinements. By a rule written before the
    fresh sets existed: test-split 11700 587 / 6 found / false against 588 / 6 (one covered marker,
    0.57 px off before, lost), every other figure within 0.001; 11800 every figure the same; a fresh
    45 MP set (11900, 24 images) the same markers and centres at 78.3 against 82.1 s in all, the
    slowest image 4.1 against 5.5 s (TRAINING.md).
    min_centre_reach: drop a refined centre where the four sectors do not meet
    (:func:`cpdetect.centre_reach.centre_reach` below this; 0 keeps every one), the classical
    detector's cut.
    min_sym180_unverified: with the centre ranker, drop a blob whose chosen centre the marker model
    does not fit (not "verified") and about which the image is not point-symmetric either
    (``sym180`` of :func:`learned.centre_choice.point_symmetry` below this; a checker centre gives
    about 0.9): nothing says a checker's centre is there. On the all-covered train-split set occ77
    (200 images) 0.1 drops 2 of 12 false markers and 2 markers placed 0.75 and 1.4 px off, none
    better placed; dev808 1 false marker fewer; dev1212 1 marker fewer (0.29 px off); dev909 and
    dev1111 (its unverified centres have sym180 0.45 or more in 95 %) unchanged. -1 keeps every one
    (the rule before 2026-11-27).
    classical_seeds: also run the classical detector on the image (13-32 % more time on 640x480
    sets); its markers that lie on a blob are tried first among the X-corner seeds, and a blob whose
    centre one of them confirms is kept whatever the instance model says. The blobs stay the
    network's: a classical marker where the network sees none adds nothing. (The classical type for centres
    the marker model does not verify instead of the shape's: type accuracy 0.968 -> 0.966 on the
    train-split dev set, so not used.)
    classical_markers: also run the classical detector on the image and report its markers where
        the network found none (no hma marker within half the smaller radius, 3 px at least), with
        their classical score, type and centre, and their outline filled into the probability map
        (the larger of the two maps within 1.5 radii); and a blob that yields no marker is cleared
        from the map even where the network is sure of it (``clear_rejected_below``) unless a
        classical marker lies on it. Off by default: it is a union of the two detectors, not the
        network's own figures (TRAINING.md gives both).
    classical_min_support: with classical_markers, a classical marker is added only where the
        network's own map (before rejected blobs are cleared) averages at least this P(marker) over
        the marker's classical outline: the network vetoes what it sees nothing of (0: no veto). On
        the train-split dev sets 808 and 909 the union added 38 markers, 6 of them false; any cut in
        (0.008, 0.017] keeps 29 true and 1 false one, and 0.01 is the round value in it.
    outline_window: a marker whose centre the classical marker model verified has its centre fitted
        once more on an ellipse as large as that model's outline allows
        (:func:`cpdetect.refine.refine_in_outline` with this ``frac``), kept where its sigma is
        the smaller; after the instance decision, so the ranker and the instance model see what
        they were fitted on. 0 turns it off.
    model_fit: with ``outline_window``, the blurred two-line checker model is fitted on the same
        ellipse too (``refine_in_outline(..., model=True)``, as the classical detector's
        ``model_fit``), kept where its sigma is the smallest; after the instance decision as well,
        so the same markers are found. On the fresh test-split sets 9000 / 9100 / 9200 / 9300 the
        shipped network's centre error went from 0.085 / 0.068 / 0.057 / 0.065 px mean to 0.077 /
        0.060 / 0.051 / 0.059 (p95 0.149 / 0.205 / 0.170 / 0.152 -> 0.118 / 0.185 / 0.165 / 0.145).
    mirror_map: the probability map returned is the mean of the image's map and its mirror image's
        (:mod:`learned.mirror_map`), where the blobs that stay are those the image's map keeps; the
        markers still come from the image's map alone. "small" (the default: the images seen at
        ``small_scales``, up to 1024 px, where the second network pass costs least), "always" or
        "never". It doubles the network time on those images; on the train-split dev sets 808 /
        909 / 1111 / 1212 pixel IoU moved by +0.0018 / +0.0047 / +0.0001 / +0.0019, and on the
        fresh test-split sets 9700 / 9800, generated after the rule for this choice was written
        down (2026-11-28, stop 47), by +0.0020 / +0.0029 (pixel F1 0.9516 -> 0.9526, 0.9650 ->
        0.9666), the same markers.
    colour_centres: for a colour image (BGR array, or a path, then read in colour), the blobs of the
        network's map that the network is sure of (mean P at least ``colour_min_mean_p``) and that
        hold no marker of the gray image are looked at again on the paint image (the max of the
        channels, :func:`cpdetect.imageio.paint_image`): centres, instance decision and type as on
        the gray image (:meth:`HMADetector._colour_instances`). The network sees gray, and finds a
        marker painted in colours of one luminance (red on grey) by its shape, but in gray there is
        no checker to put its centre on. ``extras["colour_found"]`` counts the markers it adds. The
        default since stop 48, by a rule written down before the test set was made: on the
        train-split set dev1111 it added 4 markers (all four circles painted in one luminance that
        the instance model had dropped in gray) and no false one (instance F1 0.9617 -> 0.9642,
        pixel IoU unchanged); on the fresh test-split set 10100 it changed nothing (579 / 4, F1
        0.969). A file is decoded a second time, in colour, only when such a blob exists. "small"
        (the default): only images seen at ``small_scales`` (up to 1024 px), where the rule was
        tested; on the textured 45 MP bench JPEG, read from its file, the step found nothing and
        took 10.8 s against 8.5-9.1 s (the colour decode and the texture blobs). "always", "never"
        (or true / false).
    colour_min_mean_p: the least mean P of a blob that ``colour_centres`` looks at. 0.9, the value
        of ``clear_rejected_below`` the colour rule was tested with (stop 48); its own setting since
        stop 58, so that how much of the map is cleared does not change which markers are found.
    One torch thread per detector because cpdetect parallelises over images (``--workers``): torch's
    multi-threaded kernels on an oversubscribed CPU ran 20x slower here (13.7 against 0.71 s per
    megapixel with one other busy process on 2 cores). OpenCV's threads share a busy CPU gracefully
    (2 threads beside a busy process: 4.0 s on the 45 MP bench image, 1 thread 3.9 s, 2 threads on
    an idle CPU 2.1 s), so OpenCV keeps all cores.
    """

    model_dir: str | None = None
    network: str = "default"
    large_network: str | None = None
    scales: tuple[float, ...] = (0.5, 1.0)
    small_scales: tuple[float, ...] | None = (0.5, 1.0, 1.5, 2.0)
    backend: str = "auto"
    device: str = "cpu"
    threshold: float = 0.5
    max_side: int | None = 2048
    tile: int = 2048
    overlap: int = 96
    min_radius_px: float = 3.0
    refine: str = "auto"
    drop_unrefined: bool = True
    max_sigma_px: float = 0.3
    max_sigma_verified_px: float = 0.6
    clear_rejected_below: float = 0.9
    large_clear_rejected_below: float | None = None
    large_drop_unverified_seeds: bool = True
    large_clear_unverified_seeds: bool = True
    large_classical_veto: bool = True
    large_classical_seeds: bool = True
    classical_seed_min_score: float = 0.99
    large_seed_confirm_min_score: float | None = None
    classical_centres: bool = False
    large_clear_flat_below: float = 3.0
    large_spare_reach: float | None = None
    large_spare_max_sym180: float = 0.9
    large_lower_scale: float | None = 0.25
    max_seeds: int = 3
    type_by: str = "model"
    threads: int | None = None
    instance_model: str = "auto"
    instance_threshold: float | None = None
    max_sigma_seed_px: float = 1.0
    min_blob_mean_p: float = 0.6
    min_centre_reach: float = CENTRE_REACH_MIN
    min_sym180_unverified: float = 0.1
    classical_seeds: bool = False
    classical_markers: bool = False
    classical_min_support: float = 0.01
    centre_ranker: str = "auto"
    rank_seeds: int = 8
    rank_seeds_unsure: int = 3
    rank_sure_mean_p: float = 0.85
    rank_stop: float = 0.9
    rank_stop_model: float = 0.5
    seed_pool: int = 24
    unsure_min_symmetry: float | None = 0.5
    min_seed_symmetry: float | None = 0.0
    outline_window: float = 1.0
    model_fit: bool = True
    mirror_map: str = "small"
    colour_centres: str | bool = "small"
    colour_min_mean_p: float = 0.9

    def __post_init__(self) -> None:
        object.__setattr__(self, "scales", tuple(float(s) for s in self.scales))
        default_model_dir(self.network)  # refuses a name that is not a shipped network
        if self.large_network is not None:
            default_model_dir(self.large_network, "large_network")
        # a pass at scale s holds s^2 times a tile's pixels: 50 asked 19 GB of one 1024-px tile
        if 1.0 not in self.scales or min(self.scales) <= 0 or max(self.scales) > MAX_SCALE:
            raise ValueError(f"scales must be in (0, {MAX_SCALE:g}] and include 1.0, got {self.scales}")
        if self.small_scales:
            object.__setattr__(self, "small_scales", tuple(float(s) for s in self.small_scales))
            if 1.0 not in self.small_scales or min(self.small_scales) <= 0 or max(self.small_scales) > MAX_SCALE:
                raise ValueError(f"small_scales must be in (0, {MAX_SCALE:g}] and include 1.0, got {self.small_scales}")
        else:
            object.__setattr__(self, "small_scales", None)
        if self.backend not in ("auto", "torch", "opencv"):
            raise ValueError(f"backend must be auto, torch or opencv, got {self.backend!r}")
        if self.centre_ranker not in ("auto", "none"):
            raise ValueError(f"centre_ranker must be auto or none, got {self.centre_ranker!r}")
        if min(self.rank_seeds, self.rank_seeds_unsure, self.seed_pool) < 0 or not 0.0 < self.rank_stop <= 1.0:
            raise ValueError("need rank_seeds, rank_seeds_unsure, seed_pool >= 0 and 0 < rank_stop <= 1")
        if self.unsure_min_symmetry is not None and not -2.0 <= self.unsure_min_symmetry <= 2.0:
            raise ValueError("unsure_min_symmetry must be in [-2, 2] (or None)")
        if self.min_seed_symmetry is not None and not -2.0 <= self.min_seed_symmetry <= 2.0:
            raise ValueError("min_seed_symmetry must be in [-2, 2] (or None)")
        if not -1.0 <= self.min_sym180_unverified <= 1.0:
            raise ValueError("min_sym180_unverified must be in [-1, 1]")
        if not 0.0 <= self.rank_stop_model <= 1.0:
            raise ValueError("rank_stop_model must be in [0, 1]")
        if not 0.0 <= self.classical_seed_min_score <= 1.0:
            raise ValueError("classical_seed_min_score must be in [0, 1]")
        if self.large_seed_confirm_min_score is not None and not 0.0 <= self.large_seed_confirm_min_score <= 1.0:
            raise ValueError("large_seed_confirm_min_score must be in [0, 1] (or null: off)")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError("threshold must be in (0, 1)")
        if self.max_side is not None and self.max_side < 64:
            raise ValueError("max_side must be >= 64 (or None)")
        if self.tile < 128 or self.overlap < 0 or self.tile <= 2 * self.overlap:
            raise ValueError("need tile >= 128 and 0 <= 2 * overlap < tile")
        if not (self.max_sigma_px > 0 and self.max_sigma_verified_px > 0):
            raise ValueError("max_sigma_px and max_sigma_verified_px must be positive")
        if not 0.0 <= self.clear_rejected_below <= 1.0:
            raise ValueError("clear_rejected_below must be in [0, 1]")
        if self.large_clear_rejected_below is not None and not 0.0 <= self.large_clear_rejected_below <= 1.0:
            raise ValueError("large_clear_rejected_below must be in [0, 1] (or null)")
        if not -1.0 <= self.large_spare_max_sym180 <= 1.0:
            raise ValueError("large_spare_max_sym180 must be in [-1, 1] (a correlation)")
        if self.large_lower_scale is not None and not 0.0 < self.large_lower_scale < 1.0:
            raise ValueError(f"large_lower_scale must be in (0, 1) or null, got {self.large_lower_scale}")
        if self.large_spare_reach is not None and not self.large_spare_reach > 0:
            raise ValueError("large_spare_reach must be positive (a ratio of X-corner strengths) or null (off)")
        if not 0.0 <= self.large_clear_flat_below <= 255.0:
            raise ValueError("large_clear_flat_below must be in [0, 255] (grey levels; 0 is off)")
        if not 0.0 <= self.colour_min_mean_p <= 1.0:
            raise ValueError("colour_min_mean_p must be in [0, 1]")
        if not 0.0 <= self.classical_min_support < 1.0:
            raise ValueError("classical_min_support must be in [0, 1)")
        if not 0.0 <= self.outline_window <= 2.0:
            raise ValueError("outline_window must be in [0, 2] (0: off)")
        if self.max_seeds < 0:
            raise ValueError("max_seeds must be >= 0")
        if self.type_by not in ("model", "shape"):
            raise ValueError(f"type_by must be model or shape, got {self.type_by!r}")
        if self.refine not in METHODS + ("none",):
            raise ValueError(f"unknown refine method {self.refine!r}")
        if self.instance_model not in ("auto", "none"):
            raise ValueError(f"instance_model must be auto or none, got {self.instance_model!r}")
        if self.instance_threshold is not None and not 0.0 < self.instance_threshold < 1.0:
            raise ValueError("instance_threshold must be in (0, 1) (or None)")
        if not 0.0 <= self.min_blob_mean_p < 1.0:
            raise ValueError("min_blob_mean_p must be in [0, 1)")
        if not self.max_sigma_seed_px > 0:
            raise ValueError("max_sigma_seed_px must be positive")
        if self.threads is not None and (not isinstance(self.threads, int) or self.threads < 1):
            raise ValueError(f"threads must be a positive integer (or None), got {self.threads!r}")
        if not self.min_centre_reach >= 0:
            raise ValueError("min_centre_reach must be 0 or more")
        if self.mirror_map not in ("small", "always", "never"):
            raise ValueError(f"mirror_map must be small, always or never, got {self.mirror_map!r}")
        if isinstance(self.colour_centres, bool):  # --set colour_centres=true / false
            object.__setattr__(self, "colour_centres", "always" if self.colour_centres else "never")
        if self.colour_centres not in ("small", "always", "never"):
            raise ValueError(f"colour_centres must be small, always or never, got {self.colour_centres!r}")


def _quad_from_hull(hull: np.ndarray) -> np.ndarray | None:
    peri = cv2.arcLength(hull, True)
    for eps in (0.02, 0.03, 0.045, 0.06, 0.08, 0.1):
        approx = cv2.approxPolyDP(hull, eps * peri, True)
        if len(approx) == 4:
            return approx.reshape(4, 2).astype(np.float32)
        if len(approx) < 4:
            return None
    return None


def _iou_with_polygon(mask: np.ndarray, fill: callable) -> float:
    canvas = np.zeros_like(mask)
    fill(canvas)
    inter = np.count_nonzero(canvas & mask)
    union = np.count_nonzero(canvas | mask)
    return inter / union if union else 0.0


def classify_shape(mask: np.ndarray) -> tuple[str, np.ndarray | None]:
    """"circle" or "quad" for a binary component mask (uint8 0/1), and the quadrilateral (4, 2) if any."""
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return "quad", None
    c = max(contours, key=cv2.contourArea)
    if len(c) < 6:
        return "quad", None
    hull = cv2.convexHull(c)
    ellipse = cv2.fitEllipse(c)
    iou_e = _iou_with_polygon(mask, lambda cv: cv2.ellipse(cv, ellipse, 1, -1))
    quad = _quad_from_hull(hull)
    iou_q = 0.0
    if quad is not None:
        iou_q = _iou_with_polygon(mask, lambda cv: cv2.fillPoly(cv, [np.round(quad).astype(np.int32)], 1))
    return ("circle" if iou_e >= iou_q else "quad"), quad


def checker_phase_type(gray: np.ndarray, cx: float, cy: float, radius: float, quad_img: np.ndarray | None) -> str:
    """"square" or "diagonal": compare the checker's boundary directions with the outline's edges.

    The angular profile I(theta) on a ring of 0.3..0.6 radius around the centre has a second harmonic
    whose phase gives the two boundary lines; for "square" they are parallel to the edges of the
    outline quadrilateral, for "diagonal" they run to its corners (45 degrees off in the frontal view).
    """
    if quad_img is None:
        return "square"
    n = 96
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rs = radius * np.array([0.3, 0.4, 0.5, 0.6])
    # only the rings' window is read: a float copy of a 45 MP image is 180 MB, and remap refuses
    # images of 32767 pixels a side or more; the window reaches the image's border wherever the rings
    # pass it, so replicating its border is replicating the image's
    h, w = gray.shape[:2]
    reach = float(rs[-1]) + 2.0
    x0 = int(np.clip(np.floor(cx - reach), 0, w - 1))
    y0 = int(np.clip(np.floor(cy - reach), 0, h - 1))
    x1 = int(np.clip(np.ceil(cx + reach) + 2, x0 + 1, w))
    y1 = int(np.clip(np.ceil(cy + reach) + 2, y0 + 1, h))
    win = np.asarray(gray[y0:y1, x0:x1], np.float32)
    xs = (cx - x0 + np.cos(th)[None] * rs[:, None]).astype(np.float32)
    ys = (cy - y0 + np.sin(th)[None] * rs[:, None]).astype(np.float32)
    vals = cv2.remap(win, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).mean(0)
    vals = vals - vals.mean()
    # I(theta) ~ a cos(2 theta - phi): bright sectors centred at phi / 2 (+ 180); boundaries at phi/2 +- 45
    z = np.sum(vals * np.exp(-2j * th))
    boundary = (-np.angle(z) / 2.0 + np.pi / 4) % (np.pi / 2)
    # directions from the centre to the edge midpoints of the outline
    q = np.asarray(quad_img, float)
    mids = 0.5 * (q + np.roll(q, -1, axis=0))
    edge_dirs = np.arctan2(mids[:, 1] - cy, mids[:, 0] - cx) % (np.pi / 2)
    corner_dirs = np.arctan2(q[:, 1] - cy, q[:, 0] - cx) % (np.pi / 2)

    def dist(a: np.ndarray) -> float:
        d = np.abs((a - boundary + np.pi / 4) % (np.pi / 2) - np.pi / 4)
        return float(d.mean())

    # square: boundaries point at the edge midpoints; diagonal: at the corners
    return "square" if dist(edge_dirs) <= dist(corner_dirs) else "diagonal"


def dedupe(dets: list[MarkerDetection]) -> list[MarkerDetection]:
    """Merge instances that refined onto the same X-corner (closer than a third of the smaller radius,
    at least 1 px): the larger component (the better segmented one) is kept."""
    kept: list[MarkerDetection] = []
    for d in sorted(dets, key=lambda d: -d.radius_px):
        if all(math.hypot(d.x - k.x, d.y - k.y) > max(1.0, min(d.radius_px, k.radius_px) / 3.0) for k in kept):
            kept.append(d)
    return kept


def _with_classical_markers(dets: list[MarkerDetection], prob: np.ndarray, f: float,
                            classical: DetectionResult, network: np.ndarray | None = None,
                            min_support: float = 0.0) -> tuple[list[MarkerDetection], np.ndarray]:
    """``dets`` plus the classical markers no detection lies on (closer than half the smaller
    radius, 3 px at least), and ``prob`` (P(marker) at ``f`` map pixels per image pixel) with their
    classical outlines filled in: the larger of the two maps within 1.5 radii of each added marker.
    ``network``: the network's own map (same grid, before rejected blobs are cleared); a classical
    marker is added only where it averages at least ``min_support`` over the marker's classical
    outline (see :func:`_network_support`)."""
    added = [c for c in classical.detections
             if all(math.hypot(c.x - d.x, c.y - d.y) >= max(3.0, 0.5 * min(c.radius_px, d.radius_px)) for d in dets)]
    if not added:
        return dets, prob
    ph, pw = prob.shape
    theirs = classical.probability_at(pw, ph)
    if network is not None and min_support > 0:
        added = [c for c in added if _network_support(network, theirs, f, c) >= min_support]
        if not added:
            return dets, prob
    near = np.zeros((ph, pw), np.uint8)
    for c in added:
        centre = (int(round((c.x + 0.5) * f - 0.5)), int(round((c.y + 0.5) * f - 0.5)))
        cv2.circle(near, centre, int(math.ceil(1.5 * c.radius_px * f)) + 1, 1, -1)
    if theirs is not None:
        prob = np.where(near > 0, np.maximum(prob, theirs), prob)
    return dets + added, prob


def _network_support(network: np.ndarray, theirs: np.ndarray | None, f: float, c: MarkerDetection) -> float:
    """Mean network P(marker) over the classical marker ``c``'s outline: the component of the
    classical map (``theirs``, >= 0.5) under its centre, else a disc of half its radius (map pixels,
    ``f`` per image pixel)."""
    ph, pw = network.shape
    cx, cy = _map_pixel(c.x, c.y, f, network.shape)
    r = int(math.ceil(2.0 * c.radius_px * f)) + 2
    x0, y0, x1, y1 = max(cx - r, 0), max(cy - r, 0), min(cx + r + 1, pw), min(cy + r + 1, ph)
    area = None
    if theirs is not None:
        _, lab = cv2.connectedComponents((theirs[y0:y1, x0:x1] >= 0.5).astype(np.uint8))
        k = lab[cy - y0, cx - x0]
        area = lab == k if k > 0 else None
    if area is None:
        disc = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.circle(disc, (cx - x0, cy - y0), max(1, int(round(0.5 * c.radius_px * f))), 1, -1)
        area = disc > 0
    return float(network[y0:y1, x0:x1][area].mean())


def _paint_of(image: Any) -> np.ndarray | None:
    """The paint image (:func:`cpdetect.imageio.paint_image`) of a BGR(A) array or of an image file
    (read again, in colour); None for a gray one."""
    from cpdetect.imageio import paint_image, read_image

    a = read_image(image) if isinstance(image, (str, os.PathLike)) else np.asarray(image)
    if a.ndim != 3 or a.shape[2] < 3:
        return None
    return paint_image(np.ascontiguousarray(a[:, :, :3]))


@dataclass(frozen=True)
class ClassicalVeto:
    """Where the classical detector said "not a marker" on one image: ``rejected`` (n, 2), image
    pixels, its candidates that stopped at one of :data:`CLASSICAL_VETO_STAGES`, and ``found`` (m, 2),
    the centres of the markers it kept."""

    rejected: np.ndarray
    found: np.ndarray

    @classmethod
    def from_trace(cls, trace: list[dict], found: list[MarkerDetection]) -> "ClassicalVeto":
        """From a trace of :meth:`cpdetect.classical.ClassicalDetector.detect` and its markers."""
        rej = [(t["x"], t["y"]) for t in trace if t["stage"] in CLASSICAL_VETO_STAGES]
        return cls(np.array(rej, float).reshape(-1, 2), np.array([(d.x, d.y) for d in found], float).reshape(-1, 2))

    def says_no(self, x: float, y: float, radius: float) -> bool:
        """Whether a marker of ``radius`` at (x, y) is vetoed: no classical marker within half the
        radius, and a rejected candidate within max(8 px, 0.1 radius)."""
        if len(self.found) and np.hypot(*(self.found - (x, y)).T).min() < 0.5 * radius:
            return False
        return bool(len(self.rejected)) and np.hypot(*(self.rejected - (x, y)).T).min() < max(8.0, 0.1 * radius)


def _map_pixel(x: float, y: float, f: float, shape: tuple[int, int]) -> tuple[int, int]:
    """(column, row) of the map pixel (``f`` per image pixel, map of ``shape`` (rows, columns))
    nearest to the image point (x, y), clipped into the map."""
    col = int(round((x + 0.5) * f - 0.5))
    row = int(round((y + 0.5) * f - 0.5))
    return min(max(col, 0), shape[1] - 1), min(max(row, 0), shape[0] - 1)


def _reach_of(gray: np.ndarray, b: "BlobCandidate") -> float:
    """Blob ``b``'s centre reach (:func:`centre_reach` with the blob's radius): the one its centre
    carries (the ranker measures it), else measured now."""
    c = b.centre
    return centre_reach(gray, c.x, c.y, b.radius) if c.reach is None else c.reach


def _labels_under(dets, f: float, labels: np.ndarray) -> list[int]:
    """The component label (0: background) under each detection's centre, at its map pixel."""
    return [int(labels[r, c]) for c, r in (_map_pixel(d.x, d.y, f, labels.shape) for d in dets)]


class HMADetector:
    """The learned marker detector (HMA over HRNet-OCR), registered as ``hma``."""

    name = "hma"
    Settings = HMASettings

    def __init__(self, **settings: Any):
        self.settings: HMASettings = settings_from_dataclass(HMASettings, settings)
        s = self.settings
        model_dir = Path(s.model_dir) if s.model_dir else _shipped_folder(s.network)
        from .infer import open_backend

        self.model_dir = model_dir
        self.backend = open_backend(model_dir, s.backend, s.device, s.threads)
        self.large_backend = None
        if s.large_network is not None and s.model_dir is None and s.large_network != s.network:
            self.large_backend = open_backend(_shipped_folder(s.large_network), s.backend, s.device, s.threads)
        self.instance_model = load_instance_model(model_dir) if s.instance_model == "auto" else None
        ranker = load_centre_ranker(model_dir) if s.centre_ranker == "auto" else None
        self.centre_ranker = ranker if self.instance_model is not None else None
        self.collect_options = False  # keep every centre candidate on the blobs (for fitting the ranker)

    @classmethod
    def with_backend(cls, backend: Any, instances: InstanceModel | None = None,
                     ranker: CentreRanker | None = None, **settings: Any) -> "HMADetector":
        """A detector around an already opened backend (anything with ``name`` and ``trunk(x)``),
        with an optional instance model (ignored when the setting ``instance_model`` is "none") and
        centre ranker (used with an instance model, unless ``centre_ranker`` is "none")."""
        self = cls.__new__(cls)
        self.settings = settings_from_dataclass(HMASettings, settings)
        self.model_dir = None
        self.backend = backend
        self.large_backend = None
        self.instance_model = instances if self.settings.instance_model == "auto" else None
        use_ranker = self.instance_model is not None and self.settings.centre_ranker == "auto"
        self.centre_ranker = ranker if use_ranker else None
        self.collect_options = False
        return self

    # ------------------------------------------------------------------
    def scales_for(self, width: int, height: int) -> tuple[float, ...]:
        """The inference scales for an image of this size: ``small_scales`` where its largest pass
        still fits in ``max_side`` pixels per side, else ``scales``."""
        s = self.settings
        if s.small_scales and s.max_side and max(width, height) * max(s.small_scales) <= s.max_side:
            return s.small_scales
        return s.scales

    def mirrors(self, width: int, height: int) -> bool:
        """Whether the returned map of an image of this size is the mean with its mirror image's
        (``mirror_map``)."""
        return self._applies(self.settings.mirror_map, width, height)

    def seen_downscaled(self, width: int, height: int) -> bool:
        """Whether the network sees an image of this size downscaled (longest side over ``max_side``)."""
        m = self.settings.max_side
        return m is not None and max(width, height) > m

    def clear_rejected_below_for(self, width: int, height: int) -> float:
        """The least mean P of a blob that yields no marker and stays in the returned map, for an image
        of this size: ``large_clear_rejected_below`` where the network sees it downscaled and that is
        set, else ``clear_rejected_below``."""
        s = self.settings
        if s.large_clear_rejected_below is not None and self.seen_downscaled(width, height):
            return s.large_clear_rejected_below
        return s.clear_rejected_below

    def colour_centres_for(self, width: int, height: int) -> bool:
        """Whether blobs without a marker are looked at again on the paint image for an image of this
        size (``colour_centres``: "small", the images seen at ``small_scales``)."""
        return self._applies(self.settings.colour_centres, width, height)

    def _applies(self, mode: str, width: int, height: int) -> bool:
        """A step set to "always", "never" or "small" (images seen at ``small_scales``), for an image
        of this size."""
        s = self.settings
        if mode != "small":
            return mode == "always"
        return s.small_scales is not None and self.scales_for(width, height) == s.small_scales

    def backend_for(self, width: int, height: int):
        """The network for an image of this size: ``large_network``'s where the image is seen
        downscaled (longest side over ``max_side``) and one is set, else the detector's own."""
        if self.large_backend is not None and self.seen_downscaled(width, height):
            return self.large_backend
        return self.backend

    def probability(self, gray: np.ndarray, lower: bool = False):
        """The network's map of ``gray`` (:func:`learned.infer.probability_map`); ``lower``: with the
        map fused one scale further down too, where ``large_lower_scale`` asks for it."""
        from .infer import probability_map

        s = self.settings
        h, w = gray.shape[:2]
        scales = self.scales_for(w, h)
        lower_scale = s.large_lower_scale if lower and self.seen_downscaled(w, h) else None
        if lower_scale is not None and lower_scale >= min(scales):
            lower_scale = None  # the scales reach that far down already
        return probability_map(gray, self.backend_for(w, h), scales, s.max_side, s.tile, s.overlap, lower_scale)

    def detect(self, image: Any) -> DetectionResult:
        t0 = time.perf_counter()
        s = self.settings
        source = image
        if isinstance(image, (str, os.PathLike)):
            from cpdetect.imageio import read_image

            image = read_image(image, gray=True)
        gray = as_gray_uint8(image)
        h, w = gray.shape
        if h < 8 or w < 8:
            # no marker of the least radius fits (as the classical detector finds): nothing, not an error
            return DetectionResult(detections=[], image_size=(w, h), probability=np.zeros((h, w), np.float32),
                                   seconds=time.perf_counter() - t0,
                                   extras={"backend": self.backend.name, "scales": [], "probability_factor": 1.0,
                                           "network": self._network_for(w, h)})
        downscaled = self.seen_downscaled(w, h)
        veto_on = s.large_classical_veto and downscaled
        seeds_on = self.takes_classical_seeds(w, h)
        trace: list | None = [] if veto_on else None
        classical = self._classical(source, s.classical_markers, trace) \
            if seeds_on or s.classical_markers or veto_on else None
        seeds = self.seeds_of(classical.detections) if seeds_on else None
        veto = ClassicalVeto.from_trace(trace, classical.detections) if veto_on else None
        pm = self.probability(gray, lower=True)
        witnesses = classical.detections if s.classical_markers else None
        confirmers = self.seed_confirmers_of(classical.detections, w, h) if classical is not None else None
        dets, prob = self._instances(gray, pm.prob, pm.factor, seeds, witnesses, veto, confirmers)
        colour_found = 0
        if self.colour_centres_for(w, h):
            n0 = len(dets)
            dets, prob = self._colour_instances(lambda: _paint_of(source), pm.prob, pm.factor, dets, prob, seeds,
                                                witnesses)
            colour_found = len(dets) - n0
        mirrored = self.mirrors(w, h)
        if mirrored:
            mean = mirrored_mean(gray, pm.prob, lambda g: self.probability(g).prob)
            prob = keep_blobs_of(mean, prob, s.threshold)
        if s.classical_markers:
            dets, prob = _with_classical_markers(dets, prob, pm.factor, classical, pm.prob, s.classical_min_support)
        if pm.lower is not None:
            prob = corrected_by_lower(prob, pm.lower, [_map_pixel(d.x, d.y, pm.factor, prob.shape) for d in dets],
                                      s.threshold)
        dets.sort(key=lambda d: -d.score)
        return DetectionResult(detections=dets, image_size=(w, h), probability=prob,
                               seconds=time.perf_counter() - t0,
                               extras={"backend": self.backend.name, "scales": list(self.scales_for(w, h)),
                                       "network": self._network_for(w, h),
                                       "probability_factor": pm.factor, "mirrored_map": mirrored,
                                       "colour_found": colour_found})

    def _network_for(self, width: int, height: int) -> str:
        """The name of the network an image of this size goes through: a shipped one's name, or
        "model_dir" for a folder given by the user (or a backend given to :meth:`with_backend`)."""
        s = self.settings
        if self.backend_for(width, height) is self.large_backend:
            return s.large_network
        return "model_dir" if s.model_dir or self.model_dir is None else s.network

    def _colour_instances(self, paint_of: Callable[[], np.ndarray | None], network: np.ndarray, f: float,
                          dets: list[MarkerDetection], prob: np.ndarray, seeds: list[MarkerDetection] | None,
                          witnesses: list[MarkerDetection] | None) -> tuple[list[MarkerDetection], np.ndarray]:
        """``dets`` (from the gray image) plus the markers found on the paint image (``paint_of()``, the
        max of the channels, :func:`_paint_of`; None for a gray image) on the blobs of the network's map
        ``network`` that hold none of them and that the network is sure of (mean P at least
        ``colour_min_mean_p``): centres, instance decision and type as on the gray image, but on
        paint, where a marker painted in colours of one luminance shows its checker. ``prob`` (the
        returned map) gets the network's blobs of the added markers back."""
        s = self.settings
        n, labels, stats, _ = cv2.connectedComponentsWithStats((network >= s.threshold).astype(np.uint8),
                                                               connectivity=8)
        if n <= 1:
            return dets, prob
        held = np.zeros(n, bool)
        held[_labels_under(dets, f, labels)] = True
        mean_p = np.bincount(labels.ravel(), weights=network.ravel(), minlength=n) \
            / np.maximum(stats[:, cv2.CC_STAT_AREA], 1)
        look = ~held & (mean_p >= s.colour_min_mean_p)
        look[0] = False
        if not look.any():
            return dets, prob
        paint = paint_of()  # decoded only now: most images have no such blob
        if paint is None:
            return dets, prob
        more, _ = self._instances(paint, np.where(look[labels], network, np.float32(0.0)), f, seeds, witnesses)
        added = [m for m in more
                 if all(math.hypot(m.x - d.x, m.y - d.y) > max(1.0, min(m.radius_px, d.radius_px) / 3.0) for d in dets)]
        if not added:
            return dets, prob
        back = np.zeros(n, bool)
        back[_labels_under(added, f, labels)] = True
        back[0] = False
        return dets + added, np.where(back[labels], np.maximum(prob, network), prob).astype(np.float32, copy=False)

    # ------------------------------------------------------------------
    def candidates(self, gray: np.ndarray, prob: np.ndarray, f: float,
                   loose: bool | None = None,
                   seeds: list[MarkerDetection] | None = None) -> tuple[list["BlobCandidate"], np.ndarray]:
        """Every blob of ``prob`` (P(marker) at ``f`` processing pixels per image pixel) with what
        decides about it: its centre (None when no seed refines to an acceptable X-corner, or for
        blobs under ``min_radius_px``) and its instance features; and the component label map.
        ``loose``: also give blobs whose best centre is only a refined seed (up to
        ``max_sigma_seed_px``), as an instance model needs; None = when this detector has one."""
        s = self.settings
        loose = self.instance_model is not None if loose is None else loose
        extra = [(d.x, d.y) for d in seeds] if seeds is not None else []
        binary = (prob >= s.threshold).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
        ph, pw = labels.shape
        # the blob under each classical marker, for classical_centres only
        seed_labels = _labels_under(seeds, f, labels) if seeds and s.classical_centres else []
        out: list[BlobCandidate] = []
        for k in range(1, n):
            x0, y0, bw, bh, area = (int(v) for v in stats[k])
            sl = (slice(y0, y0 + bh), slice(x0, x0 + bw))
            comp = labels[sl] == k
            p = prob[sl] * comp
            wsum = float(p.sum())
            radius = math.sqrt(area / math.pi) / f  # equal-area radius, image pixels
            yy, xx = np.mgrid[y0:y0 + bh, x0:x0 + bw]
            u, v = float((p * xx).sum() / wsum), float((p * yy).sum() / wsum)
            blob = BlobCandidate(k, (x0, y0, bw, bh), radius, wsum / area, ((u + 0.5) / f - 0.5, (v + 0.5) / f - 0.5))
            out.append(blob)
            if radius < s.min_radius_px or s.refine == "none":
                continue
            if self.instance_model is not None and blob.mean_p < s.min_blob_mean_p:
                blob.hopeless = "blob mean P low"  # the instance model would not keep it (see HMASettings)
                continue
            if self.centre_ranker is not None or self.collect_options:
                sure = blob.mean_p >= s.rank_sure_mean_p or self.collect_options
                options = self._centre_options(gray, labels, f, k, blob.bbox, radius, blob.centroid, extra,
                                               s.rank_seeds if sure else min(s.rank_seeds, s.rank_seeds_unsure),
                                               s.seed_pool, None if sure else s.unsure_min_symmetry)
                if options is None:
                    blob.hopeless = "no point-symmetric seed"  # see unsure_min_symmetry
                    continue
                blob.options = options
            if self.centre_ranker is not None:
                c = max(blob.options, key=lambda o: o[2])[0] if blob.options else None
            else:
                c = self._refined_centre(gray, labels, f, k, blob.bbox, radius, blob.centroid, loose, extra)
            if c is not None and seeds:
                c = _with_classical(c, seeds, radius)
            if seeds and s.classical_centres and not (c is not None and c.classical):
                on_blob = [d for d, lab in zip(seeds, seed_labels) if lab == k]
                if on_blob:
                    c = _classical_centre(gray, blob.options, on_blob, radius)
            blob.centre = c
            if c is not None:
                blob.features = blob_features(
                    radius, blob.mean_p, float(p.max()), float(np.count_nonzero(p >= 0.9)) / area,
                    _solidity(comp, area), x0 == 0 or y0 == 0 or x0 + bw >= pw or y0 + bh >= ph,
                    c.kind, c.sigma, math.hypot(c.x - blob.centroid[0], c.y - blob.centroid[1]) / radius,
                    c.model_score, c.sym180, c.sym90, c.blob_sym)
        return out, labels

    def _instances(self, gray: np.ndarray, prob: np.ndarray, f: float,
                   seeds: list[MarkerDetection] | None = None,
                   witnesses: list[MarkerDetection] | None = None,
                   veto: "ClassicalVeto | None" = None,
                   confirmers: list[MarkerDetection] | None = None) -> tuple[list[MarkerDetection], np.ndarray]:
        """The marker instances, and the probability map with the rejected blobs cleared (unless the
        network is sure of them, ``clear_rejected_below``, and, when ``witnesses`` is given, one of
        those markers lies on the blob); ``confirmers``: classical markers that spare a seed-kind centre
        near them the two seed rules below (:meth:`seed_confirmers_of`); ``veto``: the classical detector's
        say (``large_classical_veto``),
        whose vetoed blobs are cleared too. On images seen downscaled, sure blobs are cleared as well
        when their centre is a seed nothing confirmed (``large_clear_unverified_seeds``) or their inside
        shows one grey tone (``large_clear_flat_below``)."""
        s = self.settings
        h, w = gray.shape
        model = self.instance_model
        cut = (s.instance_threshold if s.instance_threshold is not None else model.threshold) if model else None
        blobs, labels = self.candidates(gray, prob, f, seeds=seeds)
        clear_below = self.clear_rejected_below_for(w, h)
        downscaled = self.seen_downscaled(w, h)
        drop_seeds = s.large_drop_unverified_seeds and downscaled
        clear_seeds = s.large_clear_unverified_seeds and downscaled
        flat_below = s.large_clear_flat_below if downscaled else 0.0
        spare_reach = s.large_spare_reach if downscaled else None
        witnessed = None if witnesses is None else set(_labels_under(witnesses, f, labels))
        out: list[MarkerDetection] = []
        rejected: list[int] = []
        for b in blobs:
            # a blob that yields no marker is cleared from the map unless the network is sure of it
            # (and a witness, when there are any to ask, saw a marker on it too)
            unsure = b.mean_p < clear_below or (witnessed is not None and b.label not in witnessed)
            # a centre only a refined X-corner seed gave, neither the marker model nor a classical marker
            # confirming it: on images seen downscaled mostly checkerboard and shadow corners, whatever the
            # network's confidence (large_drop_unverified_seeds drops it, large_clear_unverified_seeds
            # clears its blob)
            seed_only = b.centre is not None and b.centre.kind == "seed" and not b.centre.classical \
                and not (confirmers and _near_one(b.centre, confirmers, SEED_CONFIRM_PX))
            cx, cy = b.centroid
            score = float(np.clip(b.mean_p, 0.0, 1.0))
            sigma = max(0.5, 0.25 * b.radius)
            mtype = None
            keep = b.radius >= s.min_radius_px and not b.hopeless
            if keep and s.refine != "none":
                if b.centre is None:
                    keep = not s.drop_unrefined  # no sharp X-corner on this blob: texture, or a neighbour's
                else:
                    if model is not None:
                        score = model.probability(b.features)
                        # the classical detector's own verification stands beside the model's
                        keep = score >= cut or b.centre.classical
                    cx, cy, sigma, mtype = b.centre.x, b.centre.y, b.centre.sigma, b.centre.type
                    if keep and drop_seeds and seed_only and not self._spared(gray, b, spare_reach):
                        keep = False
                    # sym180 is measured only for the ranker's candidates (the rules leave it 0)
                    if keep and self.centre_ranker is not None and b.centre.kind != "verified" \
                            and not b.centre.classical and b.centre.sym180 < s.min_sym180_unverified:
                        keep = False
                    if keep and s.min_centre_reach > 0:
                        keep = _reach_of(gray, b) >= s.min_centre_reach
            # on images seen downscaled, where the classical scan judged this centre not a marker (a tag's
            # bit corner, a checker's) and kept none there, hma's marker was mostly false (large_classical_veto)
            vetoed = keep and veto is not None and veto.says_no(cx, cy, b.radius) \
                and not self._spared(gray, b, spare_reach)
            keep = keep and not vetoed
            if not keep:
                if unsure or (clear_seeds and seed_only) or vetoed or (
                        flat_below > 0 and self._flat(gray, labels, b, f, flat_below)):
                    rejected.append(b.label)
                continue
            if mtype is None:
                x0, y0, bw, bh = b.bbox
                p = prob[y0:y0 + bh, x0:x0 + bw] * (labels[y0:y0 + bh, x0:x0 + bw] == b.label)
                mtype = self._type_by_shape(gray, p, (x0, y0), f, b.radius, cx, cy)
            if b.centre is not None and b.centre.outline is not None and s.outline_window > 0:
                polished = refine_in_outline(gray, cx, cy, b.radius, sigma, b.centre.outline, s.outline_window,
                                             model=s.model_fit)
                if polished is not None:
                    cx, cy, sigma = polished.x, polished.y, polished.sigma_px
            cx = float(np.clip(cx, -0.5, w - 0.5))
            cy = float(np.clip(cy, -0.5, h - 0.5))
            out.append(MarkerDetection(x=cx, y=cy, score=score, type=mtype, radius_px=float(b.radius),
                                       sigma_px=float(sigma)))
        if rejected:
            clear = np.zeros(len(blobs) + 1, bool)
            clear[rejected] = True
            prob = np.where(clear[labels], np.float32(0.0), prob)
        return dedupe(out), prob

    def _spared(self, gray, b: "BlobCandidate", at_least: float | None) -> bool:
        """Whether blob ``b``'s centre reaches ``at_least`` (:func:`centre_reach` with the blob's
        radius) and is less point-symmetric than ``large_spare_max_sym180``; False when ``at_least``
        is None: ``large_spare_reach``."""
        if at_least is None or b.centre is None or not b.centre.sym180 < self.settings.large_spare_max_sym180:
            return False
        return _reach_of(gray, b) >= at_least

    @staticmethod
    def _flat(gray, labels, b: "BlobCandidate", f: float, below: float) -> bool:
        """Whether blob ``b`` shows one grey tone inside (:func:`learned.blob_tone.interior_spread`
        under ``below`` levels): no marker's paint is there (``large_clear_flat_below``)."""
        x0, y0, bw, bh = b.bbox
        spread = interior_spread(gray, labels[y0:y0 + bh, x0:x0 + bw] == b.label, b.bbox, f, b.radius)
        return spread is not None and spread < below

    def _type_by_shape(self, gray, comp_prob, origin, f, radius, cx, cy) -> str:
        """Type from the component's outline (``comp_prob``: its probabilities, 0 elsewhere, with its
        top-left corner at ``origin`` in probability-map pixels), upsampled to >= ~24 px radius;
        quadrilaterals are told apart by :func:`checker_phase_type` at the centre (cx, cy)."""
        up = max(1.0, 24.0 * f / max(radius * f, 1e-6))
        pad = 2
        pm = np.pad(comp_prob, pad)
        if up > 1.0:
            pm = cv2.resize(pm, None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR)
        kind, quad = classify_shape((pm >= self.settings.threshold).astype(np.uint8))
        if kind == "circle":
            return "circle"
        quad_img = None
        if quad is not None:
            qp = (quad + 0.5) / up - 0.5 - pad + np.array(origin, np.float32)
            quad_img = (qp + 0.5) / f - 0.5
        return checker_phase_type(gray, cx, cy, radius, quad_img)

    def takes_classical_seeds(self, width: int, height: int) -> bool:
        """Whether the classical detector's markers seed the blobs of an image of this size
        (``classical_seeds``, or ``large_classical_seeds`` on an image the network sees downscaled)."""
        s = self.settings
        return s.classical_seeds or (s.large_classical_seeds and self.seen_downscaled(width, height))

    def seed_confirmers_of(self, classical: list[MarkerDetection], width: int, height: int
                           ) -> list[MarkerDetection] | None:
        """The classical markers that, on an image the network sees downscaled, only confirm a blob's
        seed-kind centre (``large_seed_confirm_min_score``: scored at least this and under
        ``classical_seed_min_score``), sparing it ``large_drop_unverified_seeds`` and
        ``large_clear_unverified_seeds``; None when off or the image is seen whole."""
        s = self.settings
        if s.large_seed_confirm_min_score is None or not self.seen_downscaled(width, height):
            return None
        return [d for d in classical if s.large_seed_confirm_min_score <= d.score < s.classical_seed_min_score]

    def seeds_of(self, classical: list[MarkerDetection]) -> list[MarkerDetection]:
        """The classical markers that serve as seeds: those scored at least ``classical_seed_min_score``."""
        return [d for d in classical if d.score >= self.settings.classical_seed_min_score]

    def _classical(self, image: Any, with_map: bool, trace: list | None = None) -> DetectionResult:
        """The classical detector's result on ``image`` (array or path): seeds for the blobs, markers
        to add (``with_map``: with its probability map) or vetoes (``trace``: a list that receives
        where its scan left each candidate)."""
        from cpdetect.classical import BASE_SCORE_FILE, ClassicalDetector

        # the search reduction of before stop 80 (``min_search_radius_px`` None), the score trees of
        # before stop 83 (over SCORE_FEATURES alone), no held markers (before stop 84) and no second
        # outline fit without mixed rays (before stop 85): hma's settings were chosen with the seeds
        # and vetoes of those (none of the four was tried with hma)
        return ClassicalDetector(probability_map=with_map, min_search_radius_px=None, score_trees=BASE_SCORE_FILE,
                                 held_score=None, mixed_ray_retry=False).detect(image, trace=trace)

    def _refined_centre(self, gray, labels, f, k, bbox, radius, centroid, loose: bool = False,
                        extra: list[tuple[float, float]] = ()) -> "_Centre | None":
        """The marker centre of component ``k`` (bbox in probability-map pixels) in image pixels, or
        None when no seed refines to an acceptable X-corner.

        Seeds: the strongest X-corners on the (dilated) component and the probability-weighted
        centroid (a poor seed alone under perspective, occlusion or the image border). Each is refined;
        a refined centre where the classical marker model fits (four sectors and an outline, see
        :func:`cpdetect.classical.verify_marker_at`) wins, which also types it (``type_by`` "model");
        else the centroid's own refinement, if sharp (sigma <= max_sigma_px), typed by shape; else,
        when ``loose`` (for an instance model, which then judges it), the sharpest other refined seed
        up to ``max_sigma_seed_px``."""
        from cpdetect.classical import verify_marker_at
        from cpdetect.refine import refine_center_coarse_to_fine
        from cpdetect.xcorner import xcorner_seeds

        s = self.settings
        inside, box = _seed_region(labels, f, k, bbox, radius)
        seeds = [centroid] + [(x, y) for x, y, _ in xcorner_seeds(gray, box, radius, inside, s.max_seeds)]
        n_extra = 0
        if extra:
            ex = np.array(extra, float)
            ex = [tuple(p) for p in ex[inside(ex[:, 0], ex[:, 1])]]
            seeds[1:1] = ex
            n_extra = len(ex)
        checked = max(s.max_sigma_px, s.max_sigma_verified_px)
        loosest = max(checked, s.max_sigma_seed_px) if loose else checked
        fallback: _Centre | None = None
        from_classical: _Centre | None = None
        other: _Centre | None = None
        tried: list[tuple[float, float]] = []
        for i, (sx, sy) in enumerate(seeds):
            # a blob's centroid can sit tens of pixels off a large marker's centre: the coarse step
            # spares a full-resolution window that wide
            r = refine_center_coarse_to_fine(gray, sx, sy, radius, s.refine)
            if not (r.ok and r.sigma_px <= loosest):
                continue
            sigma = max(float(r.sigma_px), 1e-3)
            if r.sigma_px > checked:
                if other is None or sigma < other.sigma:
                    other = _Centre(float(r.x), float(r.y), sigma, "seed")
                continue
            if any(math.hypot(r.x - tx, r.y - ty) < 1.0 for tx, ty in tried):
                continue
            tried.append((r.x, r.y))
            sharp = r.sigma_px <= s.max_sigma_px
            found = _Centre(float(r.x), float(r.y), sigma, "centroid" if i == 0 and sharp else "seed")
            if i == 0 and sharp:
                fallback = found
            elif 1 <= i <= n_extra and from_classical is None:
                from_classical = found
            elif other is None or sigma < other.sigma:
                other = found
            if not (sharp or r.sigma_px <= s.max_sigma_verified_px):
                continue
            v = verify_marker_at(gray, r.x, r.y, radius, with_outline=True, score_file=MODEL_SCORE_FILE)
            if v is not None:
                return _Centre(found.x, found.y, sigma, "verified", v[0] if s.type_by == "model" else None, v[2],
                               outline=v[3])
        if from_classical is not None:
            return from_classical
        if fallback is not None:
            return fallback
        return other if loose else None

    def _centre_options(self, gray, labels, f, k, bbox, radius, centroid, extra: list[tuple[float, float]] = (),
                        n_seeds: int = 8, pool: int = 0,
                        min_symmetry: float | None = None) -> list[tuple["_Centre", dict, float]] | None:
        """The centre candidates of component ``k`` for the ranker: the centroid, the classical
        detector's markers on it (``extra``) and up to ``n_seeds`` X-corner seeds (the most point-
        symmetric of the ``pool`` strongest when ``pool`` exceeds ``n_seeds``; none under the
        setting ``min_seed_symmetry``), each refined (kept
        when ok with sigma <= max(max_sigma_verified_px, max_sigma_seed_px), duplicates within a
        pixel dropped), with its :func:`learned.centre_choice.candidate_features` and the ranker's
        score (0 without one). With a ranker, stops after the first scored at least ``rank_stop``.
        None, before any refinement, when ``min_symmetry`` is given, no classical marker (``extra``)
        lies on the blob and neither the centroid nor any seed of the pool has a sym180 - sym90
        (:func:`_seed_symmetry`) of at least ``min_symmetry``."""
        from cpdetect.classical import verify_marker_at
        from cpdetect.refine import refine_center_coarse_to_fine
        from cpdetect.xcorner import xcorner_seeds

        from .centre_choice import blob_symmetry, candidate_features, point_symmetry

        s = self.settings
        x0, y0, bw, bh = bbox
        comp = labels[y0:y0 + bh, x0:x0 + bw] == k
        inside, box = _seed_region(labels, f, k, bbox, radius)
        xs = xcorner_seeds(gray, box, radius, inside, max(n_seeds, pool))
        strongest = max([c for _, _, c in xs], default=1.0) or 1.0
        on_blob = []
        if extra:
            ex = np.array(extra, float)
            on_blob = [(px, py, 1.0) for px, py in ex[inside(ex[:, 0], ex[:, 1])]]
        gate = min_symmetry is not None and not on_blob
        narrow = pool and len(xs) > n_seeds
        floor = s.min_seed_symmetry
        q = [_seed_symmetry(gray, x, y, radius) for x, y, _ in xs] if gate or narrow or floor is not None else None
        if gate and max(q, default=-2.0) < min_symmetry \
                and _seed_symmetry(gray, centroid[0], centroid[1], radius) < min_symmetry:
            return None
        if floor is not None:  # before the narrowing, which keeps the most symmetric: the same seeds survive
            xs, q = [p for p, v in zip(xs, q) if v >= floor], [v for v in q if v >= floor]
        if narrow:
            xs = _most_symmetric(xs, q, n_seeds)
        seeds = [(centroid[0], centroid[1], 0.0)] + on_blob
        seeds += [(x, y, c / strongest) for x, y, c in xs]
        checked = max(s.max_sigma_px, s.max_sigma_verified_px)
        loosest = max(checked, s.max_sigma_seed_px)
        out: list[tuple[_Centre, dict, float]] = []
        for i, (sx, sy, strength) in enumerate(seeds):
            r = refine_center_coarse_to_fine(gray, sx, sy, radius, s.refine)
            if not (r.ok and r.sigma_px <= loosest):
                continue
            if any(math.hypot(r.x - o.x, r.y - o.y) < 1.0 for o, _, _ in out):
                continue
            sigma = max(float(r.sigma_px), 1e-3)
            v = verify_marker_at(gray, r.x, r.y, radius, with_outline=True, score_file=MODEL_SCORE_FILE) if r.sigma_px <= checked else None
            sym180, sym90 = point_symmetry(gray, r.x, r.y, radius)
            bsym = blob_symmetry(comp, (r.x + 0.5) * f - 0.5 - x0, (r.y + 0.5) * f - 0.5 - y0)
            sharp = r.sigma_px <= s.max_sigma_px
            kind = "verified" if v is not None else ("centroid" if i == 0 and sharp else "seed")
            c = _Centre(float(r.x), float(r.y), sigma, kind, v[0] if v is not None and s.type_by == "model" else None,
                        v[2] if v is not None else 0.0, sym180=sym180, sym90=sym90, blob_sym=bsym,
                        reach=centre_reach(gray, r.x, r.y, radius), outline=v[3] if v is not None else None)
            offset = math.hypot(r.x - centroid[0], r.y - centroid[1]) / radius
            feats = candidate_features(sigma, offset, v is not None, c.model_score, c.reach, bsym, sym180, sym90,
                                       i == 0, strength)
            score = self.centre_ranker.probability(feats) if self.centre_ranker is not None else 0.0
            out.append((c, feats, score))
            if score >= s.rank_stop and c.model_score >= s.rank_stop_model:
                break
        return out


def _seed_symmetry(gray: np.ndarray, x: float, y: float, radius: float) -> float:
    """How much the image is like an X-corner about (x, y): sym180 - sym90 of
    :func:`learned.centre_choice.point_symmetry`, in [-2, 2] (about 1.8 at a marker's centre, near 0
    at a corner of its outline or on texture)."""
    from .centre_choice import point_symmetry

    return float(np.subtract(*point_symmetry(gray, x, y, radius)))


def _most_symmetric(seeds: list[tuple[float, float, float]], q: list[float],
                    n: int) -> list[tuple[float, float, float]]:
    """The ``n`` seeds (x, y, c_hat) of the highest :func:`_seed_symmetry` ``q`` (one per seed), most
    first; ties keep the stronger seed first."""
    order = sorted(range(len(seeds)), key=lambda i: (-q[i], -seeds[i][2]))
    return [seeds[i] for i in order[:n]]


def _seed_region(labels: np.ndarray, f: float, k: int, bbox: tuple[int, int, int, int], radius: float):
    """Where the centre seeds of component ``k`` may lie: ``inside(xs, ys)`` (full-resolution
    arrays -> bool array: on the component dilated by 0.15 radius) and the full-resolution box
    (x0, y0, x1, y1) around it; ``bbox`` in probability-map pixels, ``f`` of them per image pixel."""
    x0, y0, bw, bh = bbox
    pad = max(2, int(math.ceil(0.15 * radius * f)))
    ph, pw = labels.shape
    bx0, by0 = max(0, x0 - pad), max(0, y0 - pad)
    bx1, by1 = min(pw, x0 + bw + pad), min(ph, y0 + bh + pad)
    near = cv2.dilate((labels[by0:by1, bx0:bx1] == k).astype(np.uint8), np.ones((2 * pad + 1, 2 * pad + 1), np.uint8))

    def inside(xs, ys):
        u = np.floor((xs + 0.5) * f).astype(int) - bx0
        v = np.floor((ys + 0.5) * f).astype(int) - by0
        ok = (u >= 0) & (v >= 0) & (u < near.shape[1]) & (v < near.shape[0])
        out = np.zeros(xs.shape, bool)
        out[ok] = near[v[ok], u[ok]] > 0
        return out

    return inside, (int(bx0 / f), int(by0 / f), int(math.ceil(bx1 / f)), int(math.ceil(by1 / f)))


@dataclass
class BlobCandidate:
    """One connected component of P >= threshold: its label in the component map, bbox (x0, y0, w,
    h) in processing pixels, equal-area radius and probability-weighted centroid in image pixels, mean
    P; ``centre`` and ``features`` (learned.instances.blob_features) once a centre was found."""

    label: int
    bbox: tuple[int, int, int, int]
    radius: float
    mean_p: float
    centroid: tuple[float, float]
    centre: "_Centre | None" = None
    features: dict | None = None
    # why it was dropped unrefined, "" when it was not: "blob mean P low" (under min_blob_mean_p) or
    # "no point-symmetric seed" (an unsure blob, see unsure_min_symmetry)
    hopeless: str = ""
    options: list = dataclasses.field(default_factory=list)  # (_Centre, features, ranker score) when ranked


@dataclass(frozen=True)
class _Centre:
    """A blob's centre (image pixels) with its uncertainty, how it was found (learned.instances
    CENTRE_KINDS), the marker model's type and score there (None / 0 when it does not fit)."""

    x: float
    y: float
    sigma: float
    kind: str
    type: str | None = None
    model_score: float = 0.0
    classical: bool = False  # the classical detector found a marker at this centre
    sym180: float = 0.0  # symmetry of the image and the blob about the centre (learned.centre_choice)
    sym90: float = 0.0
    blob_sym: float = 0.0
    reach: float | None = None  # centre_reach at this centre when already measured (the ranker's candidates)
    outline: np.ndarray | None = dataclasses.field(default=None, compare=False)  # the marker model's, when verified


def _classical_centre(gray: np.ndarray, options: list | None, on_blob: list[MarkerDetection],
                      radius: float) -> _Centre:
    """The centre of a blob on which the classical detector found markers (``on_blob``) that its own
    choice of centre does not agree with (``classical_centres``): the best-ranked of its centre
    ``options`` that one of them confirms (:func:`_with_classical`), else the best-scored classical
    marker's own centre, typed and scored by the classical detector, as the marker model verified it
    (a centre the blob's refinement could not give: half out of frame, where its window runs off the
    image)."""
    confirmed = [(c, rank) for c, rank in ((_with_classical(o[0], on_blob, radius), o[2]) for o in options or [])
                 if c.classical]
    if confirmed:
        return max(confirmed, key=lambda cr: cr[1])[0]
    d = max(on_blob, key=lambda m: m.score)
    return _Centre(float(d.x), float(d.y), max(float(d.sigma_px), 1e-3), "verified", d.type, float(d.score),
                   classical=True, reach=centre_reach(gray, d.x, d.y, d.radius_px))


def _with_classical(c: _Centre, found: list[MarkerDetection], radius: float) -> _Centre:
    """``c`` marked as confirmed by the classical detector when one of its markers (``found``) lies
    within max(1.5 px, a tenth of the blob radius) of it: both centres come from
    :func:`cpdetect.refine.refine_center` on the same pixels, so a confirmed one agrees closely."""
    if not _near_one(c, found, max(1.5, 0.1 * radius)):
        return c
    return dataclasses.replace(c, classical=True)


def _near_one(c: _Centre, found: list[MarkerDetection], near: float) -> bool:
    """Whether one of the markers ``found`` lies within ``near`` pixels of centre ``c``."""
    return any(math.hypot(c.x - d.x, c.y - d.y) <= near for d in found)


def _solidity(comp: np.ndarray, area: int) -> float:
    """Area of a component (bool mask) over the area of its convex hull."""
    contours, _ = cv2.findContours(comp.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return 1.0
    hull = cv2.convexHull(np.concatenate(contours))
    return float(area) / max(float(cv2.contourArea(hull)), 1.0)


__all__ = ["HMADetector", "HMASettings", "BlobCandidate", "dedupe", "default_model_dir", "shipped_weights_present",
           "classify_shape", "checker_phase_type"]
