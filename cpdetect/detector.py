"""The detector interface and its registry.

A detector is any object with ``detect(image) -> DetectionResult`` (see :class:`Detector`), built by a
factory from keyword settings. Factories are registered by name here, or by third-party packages
through the entry-point group ``cpdetect.detectors`` (the entry point names a factory: a class or a
function taking keyword settings). Unknown names and unknown settings raise :class:`UsageError`
listing what is valid: a mistyped setting is never silently ignored.
"""
from __future__ import annotations

import dataclasses
import inspect
import numbers
import re
from importlib import metadata
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from .errors import UsageError
from .types import DetectionResult

ENTRY_POINT_GROUP = "cpdetect.detectors"


@runtime_checkable
class Detector(Protocol):
    """Finds markers in one image.

    ``image`` is a uint8 array, HxW (gray) or HxWx3 (BGR, as cv2.imread gives). Implementations may
    also accept a path (str / os.PathLike) so they can decode large JPEGs at reduced scale.
    """

    name: str

    def detect(self, image: Any) -> DetectionResult: ...


_BUILTIN: dict[str, str] = {
    # name -> "module:attribute"; imported lazily so that `import cpdetect` never imports torch.
    "classical": "cpdetect.classical:ClassicalDetector",
    "hma": "learned.adapter:HMADetector",
}
_REGISTERED: dict[str, Callable[..., Detector]] = {}


def register_detector(name: str, factory: Callable[..., Detector]) -> None:
    """Register ``factory`` (a class or function taking keyword settings) under ``name``."""
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"invalid detector name {name!r}")
    _REGISTERED[name] = factory


def _entry_points() -> dict[str, Any]:
    try:
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception:  # a broken third-party distribution must not break cpdetect
        return {}
    return {ep.name: ep for ep in eps}


def available_detectors() -> list[str]:
    """Names that :func:`get_detector` accepts, sorted."""
    return sorted(set(_BUILTIN) | set(_REGISTERED) | set(_entry_points()))


def _load(target: str) -> Callable[..., Detector]:
    module_name, _, attr = target.partition(":")
    import importlib

    module = importlib.import_module(module_name)
    return getattr(module, attr)


def resolve_factory(name: str) -> Callable[..., Detector]:
    if name in _REGISTERED:
        return _REGISTERED[name]
    if name in _BUILTIN:
        return _load(_BUILTIN[name])
    eps = _entry_points()
    if name in eps:
        return eps[name].load()
    raise UsageError(f"unknown detector {name!r}; valid: {', '.join(available_detectors())}")


def factory_settings(factory: Callable[..., Any]) -> list[str]:
    """The keyword settings a factory accepts (from its settings dataclass or its signature)."""
    settings_cls = getattr(factory, "Settings", None)
    if settings_cls is not None and dataclasses.is_dataclass(settings_cls):
        return [f.name for f in dataclasses.fields(settings_cls)]
    sig = inspect.signature(factory)
    return [p.name for p in sig.parameters.values()
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name != "self"]


def _checked_factory(name: str, settings: dict[str, Any]) -> Callable[..., Detector]:
    """The factory of ``name``; UsageError for an unknown name or setting (listing the valid ones)."""
    factory = resolve_factory(name)
    valid = factory_settings(factory)
    unknown = sorted(set(settings) - set(valid))
    if unknown:
        raise UsageError(f"detector {name!r} has no setting {', '.join(map(repr, unknown))}; "
                         f"valid: {', '.join(valid) or '(none)'}")
    return factory


def get_detector(name: str, **settings: Any) -> Detector:
    """Build the detector registered as ``name`` with keyword ``settings``.

    Raises :class:`UsageError` for an unknown name or an unknown setting (listing the valid ones).
    """
    factory = _checked_factory(name, settings)
    try:
        return factory(**settings)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"detector {name!r}: {exc}") from None


def parse_settings(pairs: list[str]) -> dict[str, Any]:
    """Parse CLI ``key=value`` pairs; values are read as JSON when they parse, else kept as text."""
    import json

    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise UsageError(f"setting {pair!r} is not of the form key=value")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def settings_from_dataclass(settings_cls: type, values: dict[str, Any]):
    """Build a frozen settings dataclass, rejecting unknown keys with the list of valid ones and values of
    the wrong type (see :func:`check_setting_types`), each as a one-line :class:`UsageError`."""
    names = [f.name for f in dataclasses.fields(settings_cls)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise UsageError(f"unknown setting {', '.join(map(repr, unknown))}; valid: {', '.join(names)}")
    check_setting_types(settings_cls, values)
    return settings_cls(**values)


# annotation name -> test of a (JSON-parsed) value; an int is a valid float, a bool is not a number;
# numpy scalars count (numpy registers them as numbers.Integral / numbers.Real)
_TYPE_TESTS: dict[str, Callable[[Any], bool]] = {
    "bool": lambda v: isinstance(v, (bool, np.bool_)),
    "int": lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool),
    "float": lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool),
    "str": lambda v: isinstance(v, str),
    "None": lambda v: v is None,
}


def _annotation_kinds(f: "dataclasses.Field") -> list[str] | None:
    """The simple kinds a field accepts (``"float | None"`` -> ["float", "None"]), from its annotation
    (a type, or a string under ``from __future__ import annotations``); None when the annotation holds
    anything else (a value of that field is then not checked)."""
    ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    ann = ann.replace(" ", "")
    opt = re.fullmatch(r"(?:typing\.)?Optional\[(.+)\]", ann)
    if opt:
        ann = opt.group(1) + "|None"
    kinds = []
    for part in ann.split("|"):
        if part in _TYPE_TESTS:
            kinds.append(part)
        elif re.fullmatch(r"(?:typing\.)?(?:tuple|Tuple|list|List)(?:\[.*\])?", part):
            kinds.append("list")  # JSON gives a list; its items are not checked here
        else:
            return None
    return kinds or None


def check_setting_types(settings_cls: type, values: dict[str, Any]) -> None:
    """Raise a one-line :class:`UsageError` for a value of the wrong type (``min_score="high"`` for a
    float), judged by the field's annotation of ``settings_cls``; otherwise it would fail deep inside
    the detector. Fields with annotations other than bool/int/float/str/None/tuple/list are not checked."""
    import json

    for f in dataclasses.fields(settings_cls):
        if f.name not in values:
            continue
        kinds = _annotation_kinds(f)
        if kinds is None:
            continue
        v = values[f.name]
        if any(isinstance(v, (list, tuple)) if k == "list" else _TYPE_TESTS[k](v) for k in kinds):
            continue
        default = "" if f.default is dataclasses.MISSING else f" (default {json.dumps(f.default, default=str)})"
        raise UsageError(f"setting {f.name}={json.dumps(v, default=str)}: expected "
                         f"{' or '.join('null' if k == 'None' else k for k in kinds)}{default}")


def check_settings(name: str, settings: dict[str, Any]) -> None:
    """Check a detector's settings (names and, for a settings dataclass, types) without building the
    detector: for commands that build it late (``georef``) but should fail on a mistyped ``--set`` at
    once. Raises :class:`UsageError` (also for an unknown detector)."""
    cls = getattr(_checked_factory(name, settings), "Settings", None)
    if cls is not None and dataclasses.is_dataclass(cls):
        check_setting_types(cls, settings)


def as_gray_uint8(image: np.ndarray) -> np.ndarray:
    """HxW uint8 gray view of a gray or BGR uint8 image (raises ValueError otherwise)."""
    import cv2

    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {a.dtype}")
    if a.ndim == 2:
        return a
    if a.ndim == 3 and a.shape[2] == 3:
        return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    raise ValueError(f"expected an HxW or HxWx3 image, got shape {a.shape}")
