"""Arithmetic that gives the same bits on every machine, for observations and rewards.

An environment's observations and rewards are part of the pipeline's results (they are stored,
fingerprinted and learned from), so none of them may depend on the machine that computes them.
Two numpy routines do: ``np.linalg.norm`` and ``np.dot`` hand small vectors to BLAS, whose kernels
are chosen at run time by the CPU (and peel by the memory alignment of the array), so they
associate and fuse the products differently from one machine — or one allocation — to the next;
and numpy's transcendental ufuncs dispatch to CPU-specific SIMD code. The helpers here use only
IEEE-754 additions, multiplications and square roots in a fixed order, which are correctly
rounded everywhere, and the C library's ``cos``/``sin`` on scalars.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["cos_sin", "norm", "sum_of_squares"]


def sum_of_squares(values: ArrayLike) -> float:
    """``Σ vᵢ²``, summed from the first element to the last."""
    total = 0.0
    for v in np.asarray(values, dtype=np.float64).ravel().tolist():
        total += v * v
    return total


def norm(values: ArrayLike) -> float:
    """The Euclidean norm ``√(Σ vᵢ²)``, summed in order."""
    return math.sqrt(sum_of_squares(values))


def cos_sin(angles: Iterable[float]) -> NDArray[np.float64]:
    """``[cos θ₀, cos θ₁, …, sin θ₀, sin θ₁, …]`` from the C library, one angle at a time."""
    angles = np.asarray(angles, dtype=np.float64).ravel().tolist()
    return np.array([math.cos(a) for a in angles] + [math.sin(a) for a in angles])
