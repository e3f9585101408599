"""The torch device a user names ("auto", "cpu", "cuda", "cuda:1", ...), checked before any work.

torch itself only fails at the first tensor moved there, with an assertion ("Torch not compiled with
CUDA enabled") or a parse error, which the command line would report as an internal error; a wrong
device is the user's to fix, so it is a one-line :class:`~cpdetect.errors.UsageError` instead.
"""
from __future__ import annotations

import torch

from cpdetect.errors import UsageError


def resolve_device(name: str | torch.device) -> torch.device:
    """``name`` as a torch device: "auto" is CUDA when this torch sees a GPU, else the CPU.

    Raises UsageError for a name torch cannot parse, and for a CUDA device this torch cannot use
    (a CPU-only build, no GPU visible, or an index past the last GPU)."""
    if isinstance(name, torch.device):
        device = name
    else:
        text = str(name).strip()
        if text == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        try:
            device = torch.device(text)
        except (RuntimeError, ValueError):
            raise UsageError(f"unknown device {text!r}; valid: auto, cpu, cuda, cuda:N") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is built without CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise UsageError(f"device {str(device)!r}: {why} (torch {torch.__version__}); "
                             f"use device 'cpu' or 'auto'")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise UsageError(f"device {str(device)!r}: this machine has {count} CUDA GPU(s), "
                             f"numbered from 0")
    return device


__all__ = ["resolve_device"]
