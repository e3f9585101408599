"""Where the package data lives: ``cpdetect.data`` once installed, the checkout's ``data/`` folder otherwise."""
from __future__ import annotations

from importlib import resources
from pathlib import Path


def data_path(name: str) -> Path:
    """The file or folder ``name`` of the package data.

    Installed (``pip install .`` or editable), ``cpdetect.data`` is the checkout's ``data/`` folder
    mapped by pyproject.toml; a checkout used straight from ``PYTHONPATH`` (no install, e.g. copied to
    a machine without the dependencies' index) has no such package, and ``data/`` beside ``cpdetect/``
    is used instead.
    """
    try:
        return Path(str(resources.files("cpdetect.data") / name))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parent.parent / "data" / name


__all__ = ["data_path"]
