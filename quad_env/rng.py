"""Per-swarm random streams that the kernels own (no global RNG state).

Every swarm ``e`` has one 64-bit state ``rng[e]`` advanced by SplitMix64 (Steele, Lea & Flood 2014):
``state += 0x9E3779B97F4A7C15`` then a fixed bit mix gives the next output. The kernels visit
swarms and drones in a fixed order, so one seed fixes every draw: same seed, bit-identical transitions,
whatever else runs in the process (numba's own ``np.random`` state is per thread and shared, so it is
not used). Initial states come from ``numpy.random.SeedSequence(seed)``, so swarms get independent
streams.

Normals use the ziggurat method (Marsaglia & Tsang 2000, with Doornik's 2005 layout of 128 layers):
one 64-bit draw per normal about 98.8% of the time, so noise costs a few ns per number.
"""
from __future__ import annotations

import numpy as np

from quad_env.jit_cache import njit  # numba's njit, cached under the sources' hash

_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_TO_UNIT = 1.0 / 9007199254740992.0  # 2^-53


def seed_streams(seed: int, num_streams: int) -> np.ndarray:
    """Independent initial states ``uint64 [num_streams]`` derived from one integer seed."""
    if not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    return np.random.SeedSequence(int(seed)).generate_state(num_streams, dtype=np.uint64)


@njit(cache=True, inline="always")
def mix64(z):
    """SplitMix64 output function of an advanced state."""
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def next_u64(rng, e):
    """Advance stream ``e`` and return its next 64-bit output."""
    z = rng[e] + _GAMMA
    rng[e] = z
    return mix64(z)


@njit(cache=True, inline="always")
def uniform(rng, e):
    """Uniform float64 in [0, 1) with 53 random bits."""
    return float(next_u64(rng, e) >> _S11) * _TO_UNIT


# ---------------------------------------------------------------- ziggurat tables
_ZIG_LAYERS = 128
_ZIG_R = 3.442619855899  # start of the tail
_ZIG_V = 9.91256303526217e-3  # area of each layer


def _ziggurat_tables():
    """Layer edges x[0..128] (x[0] = base strip width V / f(R), x[1] = R, x[128] = 0) and x[i+1] / x[i]."""
    x = np.zeros(_ZIG_LAYERS + 1)
    f = np.exp(-0.5 * _ZIG_R * _ZIG_R)
    x[0] = _ZIG_V / f
    x[1] = _ZIG_R
    for i in range(2, _ZIG_LAYERS):
        x[i] = np.sqrt(-2.0 * np.log(_ZIG_V / x[i - 1] + f))
        f = np.exp(-0.5 * x[i] * x[i])
    ratio = x[1:] / x[:-1]
    return x, ratio


_ZIG_X, _ZIG_RATIO = _ziggurat_tables()
_LOW7 = np.uint64(0x7F)


@njit(cache=True)
def _normal_slow(state, u, layer):
    """The rare ziggurat branches (about 1.2% of draws): a wedge test or the tail. Returns (x, state)."""
    while True:
        if layer == 0:  # base strip: draw from the tail x > R
            while True:
                state += _GAMMA
                x = np.log(1.0 - float(mix64(state) >> _S11) * _TO_UNIT) / _ZIG_R
                state += _GAMMA
                y = np.log(1.0 - float(mix64(state) >> _S11) * _TO_UNIT)
                if -2.0 * y >= x * x:
                    return (x - _ZIG_R if u < 0.0 else _ZIG_R - x), state
        x = u * _ZIG_X[layer]  # a wedge: accept under the density
        f0 = np.exp(-0.5 * (_ZIG_X[layer] * _ZIG_X[layer] - x * x))
        f1 = np.exp(-0.5 * (_ZIG_X[layer + 1] * _ZIG_X[layer + 1] - x * x))
        state += _GAMMA
        if f1 + float(mix64(state) >> _S11) * _TO_UNIT * (f0 - f1) < 1.0:
            return x, state
        # rejected: a fresh draw
        state += _GAMMA
        z = mix64(state)
        layer = int(z & _LOW7)
        u = 2.0 * (float(z >> _S11) * _TO_UNIT) - 1.0
        if abs(u) < _ZIG_RATIO[layer]:
            return u * _ZIG_X[layer], state


@njit(cache=True, inline="always")
def normal_from(state):
    """One standard normal from a stream state held in a local variable: returns (x, new state).

    Kernels load ``rng[e]`` once, draw several numbers and store the state back: the draws then do not
    wait on each other through memory.
    """
    state += _GAMMA
    z = mix64(state)
    layer = int(z & _LOW7)  # bits 0-6 pick the layer ...
    u = 2.0 * (float(z >> _S11) * _TO_UNIT) - 1.0  # ... bits 11-63 the signed position in it
    if abs(u) < _ZIG_RATIO[layer]:  # inside the layer's rectangle: accept at once
        return u * _ZIG_X[layer], state
    return _normal_slow(state, u, layer)


@njit(cache=True)
def normal(rng, e):
    """One standard normal from stream ``e`` (ziggurat)."""
    x, rng[e] = normal_from(rng[e])
    return x


@njit(cache=True)
def normal_pair(rng, e):
    """Two independent standard normals."""
    return normal(rng, e), normal(rng, e)


@njit(cache=True)
def fill_normals(rng, e, out):
    """Fill the 1-D array ``out`` with standard normals from stream ``e`` (tests, batch draws)."""
    for k in range(out.shape[0]):
        out[k] = normal(rng, e)


# ---------------------------------------------------------------- plain-Python reference (tests)
_M64 = (1 << 64) - 1


def reference_next_u64(state: int):
    """Pure-Python SplitMix64: returns (new_state, output)."""
    state = (state + 0x9E3779B97F4A7C15) & _M64
    z = state
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _M64
    return state, z ^ (z >> 31)
