import ast
import os
import platform
import subprocess
import sys
from pathlib import Path

import service
from service.process import KERNEL_SOURCES, keep_freed_buffers, numba_cache_dir


def test_numba_cache_dir_follows_every_kernel_source(tmp_path):
    folders = (tmp_path / "kernels", tmp_path / "stages")
    for folder in folders:
        folder.mkdir()
        (folder / "a.py").write_text("x = 1\n")
    (folders[1] / "b.py").write_text("y = 2\n")
    first = numba_cache_dir(folders, tmp_path / "cache")
    assert first.parent == tmp_path / "cache" and first.name.startswith("numba-")
    assert numba_cache_dir(folders, tmp_path / "cache") == first  # stable
    (folders[1] / "b.py").write_text("y = 3\n")  # an inlined helper's module changes
    second = numba_cache_dir(folders, tmp_path / "cache")
    assert second != first
    (folders[0] / "a.py").rename(folders[0] / "c.py")  # the same text under another name
    assert numba_cache_dir(folders, tmp_path / "cache") != second


def test_every_module_with_kernels_is_in_the_digest():
    package = Path(service.__file__).parent
    with_kernels = {p.parent for p in package.rglob("*.py") if any(d in p.read_text() for d in ("numba.njit", "@njit"))}
    assert with_kernels <= set(KERNEL_SOURCES)


def _run(code: str, env: dict[str, str]) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_import_changes_nothing_and_configure_sets_defaults_that_an_explicit_environment_overrides(tmp_path):
    show = "import os; print(os.environ.get('NUMBA_CACHE_DIR', '-'), os.environ.get('OMP_WAIT_POLICY', '-'))"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "OMP_WAIT_POLICY")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    assert _run("import service, service.layout, service.pipelines; " + show, env) == ["-", "-"]
    cache, wait = _run("from service.process import configure; configure(); " + show, env)
    assert cache.startswith(str(tmp_path / "mcdenoise" / "numba-")) and wait == "PASSIVE"
    env.update(NUMBA_CACHE_DIR=str(tmp_path / "mine"), OMP_WAIT_POLICY="ACTIVE")
    explicit = _run("from service.process import configure; configure(); " + show, env)
    assert explicit == [str(tmp_path / "mine"), "ACTIVE"]


def test_kernels_imported_before_configure_cache_in_the_versioned_folder(tmp_path):
    # numba fixes a kernel's cache location at import; its default (beside the sources, keyed on each
    # kernel's own file only) would serve kernels built from old helpers
    code = (
        "from service.stages.emission import _add_kernel\n"
        "from service.process import configure\n"
        "configure()\n"
        "print(_add_kernel._cache._cache_path)"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    assert _run(code, env)[0].startswith(str(tmp_path / "mcdenoise" / "numba-"))


def test_the_command_line_configures_the_process(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "OMP_WAIT_POLICY")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    code = ("import os, sys; from service.cli import main; main(['pipelines']); "
            "print(os.environ['NUMBA_CACHE_DIR'], file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stderr.strip().startswith(str(tmp_path / "mcdenoise" / "numba-"))


def test_keep_freed_buffers_applies_on_glibc():
    assert keep_freed_buffers() is (sys.platform == "linux" and platform.libc_ver()[0] == "glibc")


def _repository_imports(root: Path) -> dict[str, set[str]]:
    """module name -> the repository modules it imports (any `import`/`from` in its source), for service,
    bench, models and export."""
    modules = {}
    for folder in ("service", "bench", "models", "export"):
        for path in (root / folder).rglob("*.py"):
            parts = path.relative_to(root).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            targets = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
            found |= {t for t in targets if t in modules}
        graph[name] = found
    return graph


def test_every_entry_point_that_runs_kernels_configures_the_process():
    """A command of the repository (a module with `main` or a `__main__` block) whose imports reach the
    service's numba kernels calls `configure()`: without it they cache beside the sources (keyed on their
    own file only) and OpenMP busy-waits. A `__main__` that only calls another module's `main` is exempt."""
    root = Path(service.__file__).resolve().parents[1]
    graph = _repository_imports(root)
    kernels = {m for m in graph if m.split(".")[:2] in (["service", "stages"], ["service", "regression"],
                                                         ["service", "kernels"])}

    def reaches(module: str, seen: set[str]) -> bool:
        if module in kernels:
            return True
        seen.add(module)
        return any(reaches(m, seen) for m in graph[module] - seen)

    missing = []
    for module in graph:
        path = root / Path(*module.split(".")).with_suffix(".py")
        if not path.is_file():
            continue
        text = path.read_text()
        command = "def main(" in text or 'if __name__ == "__main__"' in text
        if command and "configure()" not in text and "def main(" in text and reaches(module, set()):
            missing.append(module)
    assert sorted(missing) == []


def test_the_server_caps_numbas_threads_before_they_start(tmp_path):
    code = (
        "import threading, numba\n"
        "from service.cli.serve import limit_threads\n"
        "from service import pipelines\n"
        "from service.warmup import warm_up\n"
        "limit_threads(1)\n"
        "warm_up(pipelines.get('bilateral'))\n"
        "seen = []\n"
        "t = threading.Thread(target=lambda: seen.append(numba.get_num_threads())); t.start(); t.join()\n"
        "print(numba.get_num_threads(), seen[0])"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS") and k != "MCDENOISE_ORT_THREADS"}
    assert _run(code, env) == ["1", "1"]
