"""service/ must import and run with neither torch nor mitsuba installed."""

import subprocess
import sys

BLOCKER = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('torch', 'mitsuba', 'drjit', 'onnx'):
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
import pkgutil, importlib, service
for mod in pkgutil.walk_packages(service.__path__, 'service.'):
    if mod.name != 'service.__main__':
        importlib.import_module(mod.name)
from service import pipelines
print(len(pipelines.names()))
"""


def test_service_imports_without_torch_or_mitsuba():
    run = subprocess.run([sys.executable, "-c", BLOCKER], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr
    assert int(run.stdout.strip()) >= 1
