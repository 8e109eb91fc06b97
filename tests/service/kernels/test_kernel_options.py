"""House rule for the numba kernels (service/stages, service/regression, service/kernels): numpy's error model.

numba's default (Python's) error model checks every float division for a zero divisor and raises
ZeroDivisionError; that branch keeps LLVM from vectorising the loop around it. The signed log1p of
`cross_regression.pack_buffers` ran scalar because of it: ~14 ms for one buffer's 2.8 M values at 1280x720
on one core, ~1.1 ms vectorised. Functions inlined at the numba level (inline="always") are compiled with
their caller's options, so only the others are checked."""

import importlib
import pkgutil

from numba.core.registry import CPUDispatcher

from service.process import KERNEL_SOURCES


def _kernels():
    for folder in KERNEL_SOURCES:
        for info in pkgutil.iter_modules([str(folder)]):
            module = importlib.import_module(f"service.{folder.name}.{info.name}")
            for name, value in vars(module).items():
                if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                    yield f"{module.__name__}.{name}", value.targetoptions


def test_every_kernel_uses_numpys_error_model():
    kernels = dict(_kernels())
    assert "service.stages.cross_regression._pack_buffers_kernel" in kernels  # the scan sees the kernels
    assert "service.regression.box._box_solve_kernel" in kernels
    missing = [name for name, options in kernels.items()
               if options.get("inline", "never") != "always" and options.get("error_model") != "numpy"]  # fmt: skip
    assert missing == []
