"""Argument types shared by the commands."""
from __future__ import annotations

import argparse


def seed_arg(text: str) -> int:
    """A random seed: a non-negative integer (NumPy's generators refuse negative ones, which ended in
    'internal error: ValueError: expected non-negative integer')."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a non-negative integer, got {value}")
    return value
