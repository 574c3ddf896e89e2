"""The one check of actions, shared by every API (``VecQuadEnv``, the gymnasium envs, PettingZoo).

An action is 4 real numbers (rotor commands, nominally in [-1, 1]; the kernels clip, motor = (a + 1) / 2).
Accepted: int and float arrays (or nested lists) of the expected shape, every entry finite. Refused with a
message naming what was given and what is expected: a wrong shape, NaN / inf, complex numbers, strings,
booleans, objects. Finite values outside [-1, 1], however large (1e300), are clipped like any other: the
check runs in the input's own dtype, never after a narrowing cast that could turn a large number into inf.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

REAL_KINDS = "iuf"  # signed and unsigned ints, floats


def check_actions(actions, shape: Tuple[int, ...], what: str = "actions",
                  out: Optional[np.ndarray] = None) -> np.ndarray:
    """``actions`` as a C-contiguous float32 or float64 array of ``shape``, or a ValueError / TypeError.

    float32 and float64 C-contiguous arrays are returned as they are (no copy); anything else (ints, another
    memory order) is converted to float64, exactly for every float32 or float64 value, so a Fortran-ordered or
    float32 copy of the same actions steps the simulator the same way. ``out`` (float64, ``shape``) receives
    the conversion instead of a new array (a preallocated buffer in the step loop).
    """
    a = actions if isinstance(actions, np.ndarray) else np.asarray(actions)
    if a.dtype.kind not in REAL_KINDS:
        raise TypeError(f"{what} must be real numbers (an int or float array of shape {shape}), got dtype {a.dtype}"
                        + (f" ({a.ravel()[0]!r}...)" if a.size else ""))
    if a.shape != tuple(shape):
        raise ValueError(f"{what} must have shape {tuple(shape)}, got {a.shape}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        bad = np.flatnonzero(~np.isfinite(a.reshape(len(a), -1) if a.ndim > 1 else a[None]).all(axis=1))
        where = f" (rows {bad[:10].tolist()}{'...' if bad.size > 10 else ''})" if a.ndim > 1 else ""
        raise ValueError(f"{what} contain NaN or inf{where}")
    if a.dtype in (np.float32, np.float64) and a.flags.c_contiguous:
        return a
    if out is None:
        return np.ascontiguousarray(a, dtype=np.float64)
    np.copyto(out, a, casting="unsafe")
    return out
