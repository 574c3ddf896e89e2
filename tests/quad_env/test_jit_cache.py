"""numba's cache is keyed on the package's sources: a change to a file a kernel depends on, but does not live in,
never leaves the old compiled kernel running."""
import os
import subprocess
import sys
import textwrap

import numba

import quad_env
from quad_env import jit_cache

KERNEL = """
import sys
sys.path.insert(0, {root!r})
from pkg.jit_cache import keyed_cache
with keyed_cache() as folder:
    from pkg.kernels import scaled
print(scaled(2.0), folder)
"""


def make_package(root, constant):
    pkg = root / "pkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "jit_cache.py").write_text(open(jit_cache.__file__).read())
    (pkg / "params.py").write_text(f"SCALE = {constant}\n")  # what the kernel inlines, in another file
    (pkg / "kernels.py").write_text(textwrap.dedent("""
        from numba import njit
        from pkg.params import SCALE

        @njit(cache=True)
        def scaled(x):
            return SCALE * x
    """))


def run(root, cache_root):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_root)}
    out = subprocess.run([sys.executable, "-c", KERNEL.format(root=str(root))], capture_output=True, text=True,
                         env=env, check=True).stdout.split()
    return float(out[0]), out[1]


def test_a_change_to_a_dependency_alone_recompiles(tmp_path):
    cache = tmp_path / "cache"
    make_package(tmp_path, 3.0)
    assert run(tmp_path, cache)[0] == 6.0
    value, folder = run(tmp_path, cache)  # served from the cache
    assert value == 6.0 and any(os.scandir(folder))
    make_package(tmp_path, 5.0)  # kernels.py untouched: numba's own check would serve 6.0 again
    value, new_folder = run(tmp_path, cache)
    assert value == 10.0 and new_folder != folder
    make_package(tmp_path, 3.0)  # back to the first version: its compiled kernels are found again
    assert run(tmp_path, cache) == (6.0, folder)


def test_hash_covers_every_source_file(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    first = jit_cache.source_hash(tmp_path)
    (tmp_path / "b.py").write_text("y = 3\n")
    assert jit_cache.source_hash(tmp_path) != first
    (tmp_path / "b.py").write_text("y = 2\n")
    assert jit_cache.source_hash(tmp_path) == first


def test_quad_env_kernels_cache_under_its_source_hash_and_numba_is_restored():
    from quad_env import kernels

    expected = str(jit_cache.cache_root() / jit_cache.source_hash())
    locator = kernels.step_kernel._cache._cache_path
    assert locator.startswith(expected)
    assert numba.config.CACHE_DIR != expected  # other numba users keep their setting
    assert quad_env.VecQuadEnv is not None


def test_the_keyed_njit_caches_under_the_hash_however_the_module_is_imported(tmp_path):
    """A kernel module that decorates with ``jit_cache.njit`` needs no ``keyed_cache()`` block around its import:
    a change to a dependency alone still selects a fresh cache folder."""
    cache = tmp_path / "cache"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        from pkg.kernels import scaled
        print(scaled(2.0), scaled._cache._cache_path)
    """)

    def write(constant):
        make_package(tmp_path, constant)
        kernels = (tmp_path / "pkg" / "kernels.py").read_text()
        (tmp_path / "pkg" / "kernels.py").write_text(kernels.replace("from numba import njit",
                                                                     "from pkg.jit_cache import njit"))

    def run_plain():
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                             check=True).stdout.split()
        return float(out[0]), out[1]

    write(3.0)
    value, path = run_plain()
    assert value == 6.0 and path.startswith(str(cache / jit_cache.source_hash(tmp_path / "pkg")))
    write(5.0)  # only the inlined constant changes
    value, new_path = run_plain()
    assert value == 10.0 and new_path != path


def test_light_imports_load_neither_numba_nor_torch():
    """``import quad_env`` (config and layout) loads neither; ``encoders`` needs the layout only, so no numba;
    ``swarm_appo.config`` no torch (it loads them only to validate a config)."""
    def loaded(statement, modules):
        code = f"import sys\n{statement}\nprint(*[m in sys.modules for m in {modules!r}])"
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()

    assert loaded("import quad_env", ["numba", "torch"]) == ["False", "False"]
    assert loaded("import encoders", ["numba"]) == ["False"]
    assert loaded("import swarm_appo.config", ["torch", "numba"]) == ["False", "False"]
    assert loaded("from quad_env import VecQuadEnv", ["numba"]) == ["True"]  # the simulator on first use


def test_copies_of_the_same_sources_share_compiled_kernels_and_other_numba_users_are_untouched(tmp_path):
    """numba's own locator files a kernel under its file's absolute path, so each copy of the package (a clean
    clone, a Ray job's unpacked working directory on each node) compiled from scratch; the keyed locator files it
    under the sources' hash. A kernel outside the package still caches where numba puts it."""
    cache = tmp_path / "cache"
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "other_kernels.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef plus(x):\n"
                                              "    return x + 1.0\n")
    script = textwrap.dedent("""
        import sys
        sys.path[:0] = [{copy!r}, {foreign!r}]
        from pkg.kernels import scaled
        from other_kernels import plus
        print(scaled(2.0), sum(scaled.stats.cache_hits.values()), scaled._cache._cache_path,
              plus(1.0), plus._cache._cache_path)
    """)

    def run_copy(name, constant):
        copy = tmp_path / name
        copy.mkdir()
        make_package(copy, constant)
        kernels = (copy / "pkg" / "kernels.py").read_text()
        (copy / "pkg" / "kernels.py").write_text(kernels.replace("from numba import njit",
                                                                 "from pkg.jit_cache import njit"))
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
        out = subprocess.run([sys.executable, "-c", script.format(copy=str(copy), foreign=str(foreign))],
                             capture_output=True, text=True, env=env, check=True).stdout.split()
        return float(out[0]), int(out[1]), out[2], float(out[3]), out[4]

    value, hits, path, plus, plus_path = run_copy("clone_a", 3.0)
    assert (value, hits, plus) == (6.0, 0, 2.0)  # compiled
    value, hits, path_b, _, _ = run_copy("clone_b", 3.0)  # the same sources elsewhere: loaded, not compiled
    assert (value, hits, path_b) == (6.0, 1, path)
    value, hits, path_c, _, _ = run_copy("clone_c", 5.0)  # other sources: a fresh folder, compiled
    assert (value, hits) == (10.0, 0) and path_c != path
    assert path.startswith(str(cache / jit_cache.source_hash(tmp_path / "clone_a" / "pkg")))
    assert not plus_path.startswith(path.rsplit(os.sep, 1)[0]), "a foreign kernel must keep numba's locator"
