import os
import platform
import subprocess
import sys

from service.process import keep_freed_buffers, numba_cache_dir


def test_numba_cache_dir_follows_every_kernel_source(tmp_path):
    sources = tmp_path / "stages"
    sources.mkdir()
    (sources / "a.py").write_text("x = 1\n")
    (sources / "b.py").write_text("y = 2\n")
    first = numba_cache_dir(sources, tmp_path / "cache")
    assert first.parent == tmp_path / "cache" and first.name.startswith("numba-")
    assert numba_cache_dir(sources, tmp_path / "cache") == first  # stable
    (sources / "b.py").write_text("y = 3\n")  # an inlined helper's module changes
    assert numba_cache_dir(sources, tmp_path / "cache") != first


def test_import_sets_defaults_but_an_explicit_environment_wins(tmp_path):
    code = "import os, service; print(os.environ['NUMBA_CACHE_DIR']); print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "OMP_WAIT_POLICY")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    cache, wait = out.stdout.split()
    assert cache.startswith(str(tmp_path / "mcdenoise" / "numba-")) and wait == "PASSIVE"
    env.update(NUMBA_CACHE_DIR=str(tmp_path / "mine"), OMP_WAIT_POLICY="ACTIVE")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [str(tmp_path / "mine"), "ACTIVE"]


def test_keep_freed_buffers_applies_on_glibc():
    assert keep_freed_buffers() is (sys.platform == "linux" and platform.libc_ver()[0] == "glibc")


def test_the_kernels_cache_in_the_versioned_folder_even_when_numba_came_first(tmp_path):
    # numba reads NUMBA_CACHE_DIR when it is imported; imported before `service`, its default caches
    # (beside the sources, keyed on each kernel's own file only) would serve kernels built from old helpers
    code = (
        "import numba, service\n"
        "from service.stages.emission import _add_kernel\n"
        "print(_add_kernel._cache._cache_path)"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip().startswith(str(tmp_path / "mcdenoise" / "numba-"))
