"""Predicates for numbers read from user files (YAML, JSON, HDF5 attributes): what counts as a
real number before a value reaches arithmetic, numpy or a device.

A bool is no number here (YAML's ``yes`` and JSON's ``true`` are not 1), nor is text, NaN or inf.
"""

from __future__ import annotations

import math

import numpy as np


def is_number(value) -> bool:
    """Whether ``value`` is an int or a float (numpy's too), not a bool; NaN and inf included."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def whole_number(value) -> bool:
    """Whether ``value`` is an int (numpy's too), not a bool, and >= 0: a seed, a count."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) and bool(value >= 0)


def real_number(value) -> bool:
    """Whether ``value`` is a finite real number: an int or a float (numpy's too), not a bool, NaN or inf,
    nor an int beyond float's range (JSON and YAML read a 400-digit number as an exact int)."""
    if not is_number(value):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def real_numbers(values, n: int) -> bool:
    """Whether ``values`` is a list, tuple or 1-D array of ``n`` finite real numbers (``real_number``)."""
    if isinstance(values, np.ndarray) and values.ndim == 1:
        values = values.tolist()
    return isinstance(values, (list, tuple)) and len(values) == n and all(map(real_number, values))
