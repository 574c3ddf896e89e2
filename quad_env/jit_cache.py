"""numba's on-disk cache, keyed on the package's sources, so it never serves stale machine code.

numba checks a cached kernel against its *defining* file only (its modification time and size). The kernels
in ``kernels.py`` inline constants from ``params.py`` and helpers from ``rng.py``: after a change to one of
those alone, numba would keep loading the old compiled kernels. So the cache lives in a folder named after a
hash of every source file of the package: any change to any of them selects a fresh folder (and recompiles
once), and going back to an earlier version finds its folder again.

The root is ``$NUMBA_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/swarm_appo/numba`` (``~/.cache/...``).
Every kernel module decorates with this module's ``njit`` (numba's ``njit``, defined inside ``keyed_cache()``),
so a kernel caches in the keyed folder however its module is imported (``quad_env/__init__.py`` imports nothing
heavy: ``import quad_env`` and the observation layout need neither numba nor the kernels).
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import os
from pathlib import Path
from typing import Iterator

PACKAGE_DIR = Path(__file__).resolve().parent


def source_hash(package_dir: Path = PACKAGE_DIR) -> str:
    """16 hex digits of a SHA-256 over the names and contents of the package's ``*.py`` files."""
    h = hashlib.sha256()
    for path in sorted(Path(package_dir).glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def cache_root() -> Path:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "swarm_appo" / "numba"


@contextlib.contextmanager
def keyed_cache(package_dir: Path = PACKAGE_DIR) -> Iterator[Path]:
    """Kernels defined inside this block cache in ``<root>/<source hash>``; numba's setting is restored after
    (numba picks a kernel's cache folder when the kernel is defined), so other numba users are unaffected."""
    import numba

    previous = numba.config.CACHE_DIR
    folder = cache_root() / source_hash(package_dir)
    numba.config.CACHE_DIR = str(folder)
    try:
        yield folder
    finally:
        numba.config.CACHE_DIR = previous


@functools.lru_cache(maxsize=None)
def _hash_of(package_dir: Path) -> str:
    return source_hash(package_dir)  # once per process: the kernels of one process come from one version


def njit(*args, **options):
    """``numba.njit(**options)`` (the kernels pass ``cache=True``), defined inside ``keyed_cache()`` so the
    kernel caches in the folder of this version of the sources. Use as ``@njit(cache=True)`` or ``@njit``."""
    import numba

    def decorate(fn):
        previous = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = str(cache_root() / _hash_of(PACKAGE_DIR))
        try:
            return numba.njit(**options)(fn)
        finally:
            numba.config.CACHE_DIR = previous

    if args and callable(args[0]) and not options:
        return decorate(args[0])
    return decorate
