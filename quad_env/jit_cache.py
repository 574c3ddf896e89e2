"""numba's on-disk cache, keyed on the package's sources, so it never serves stale machine code.

numba checks a cached kernel against its *defining* file only (its modification time and size). The kernels
in ``kernels.py`` inline constants from ``params.py`` and helpers from ``rng.py``: after a change to one of
those alone, numba would keep loading the old compiled kernels. So the cache lives in a folder named after a
hash of every source file of the package: any change to any of them selects a fresh folder (and recompiles
once), and going back to an earlier version finds its folder again.

The folder does not depend on where the package lies: numba's own locator files a kernel under a hash of its
file's absolute path, so every copy of the same sources (a clean clone, the working directory a Ray job unpacks
on each node) compiled from scratch. ``_KeyedLocator`` files this package's kernels under
``<root>/<source hash>/<package name>`` with the source hash as the freshness stamp: any copy of one version
of the sources shares one set of compiled kernels. Other numba users keep numba's locators.

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


@functools.lru_cache(maxsize=None)
def _install_locator(package_dir: Path) -> bool:
    """Put a locator for ``package_dir``'s kernels first in numba's list (once per process and package copy).
    False where numba's internals differ from the ones this was written against (numba 0.59-0.68): the kernels
    then cache path-keyed (``njit`` below sets the folder), which is slower to warm but as correct."""
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)  # (renamed in 0.6x)
    base = getattr(caching, "_CacheLocator", None)
    if base is None or not isinstance(getattr(impl, "_locator_classes", None), list):
        return False

    class _KeyedLocator(base):
        """This package's kernels, in a folder named after the sources' hash and the package, not its path."""

        def __init__(self, py_func):
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(cache_root() / _hash_of(package_dir) / package_dir.name)

        def get_cache_path(self):
            return self._cache_path

        def get_source_stamp(self):
            return _hash_of(package_dir)  # the folder is per version already; this guards a hand-copied index

        def get_disambiguator(self):
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            if Path(py_file).resolve().parent != package_dir:
                return None  # someone else's kernel: numba's own locators
            self = cls(py_func)
            try:
                self.ensure_cache_path()
            except OSError:  # not writable: let numba's locators find a place
                return None
            return self

    impl._locator_classes.insert(0, _KeyedLocator)
    return True


def njit(*args, **options):
    """``numba.njit(**options)`` (the kernels pass ``cache=True``) whose cache is the folder of this version of
    the sources, wherever the package lies. Use as ``@njit(cache=True)`` or ``@njit``."""
    import numba

    _install_locator(PACKAGE_DIR)

    def decorate(fn):
        previous = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = str(cache_root() / _hash_of(PACKAGE_DIR))  # for numba's locators (fallback)
        try:
            return numba.njit(**options)(fn)
        finally:
            numba.config.CACHE_DIR = previous

    if args and callable(args[0]) and not options:
        return decorate(args[0])
    return decorate
