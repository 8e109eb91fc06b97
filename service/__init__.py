"""mcdenoise serving side: frames, EXR I/O, classical stages, pipelines, ONNX runtime and HTTP API.

Imports neither torch nor mitsuba."""

import os

# numba's parallel kernels run on OpenMP (thread-safe: the HTTP service steps frames from a thread pool,
# which numba's `workqueue` layer does not allow). OpenMP's default busy-wait between parallel regions
# costs 3-9x on a shared 2-core machine (measured on svgf at 256x256); passive waiting avoids it.
# Set before any numba kernel first loads the OpenMP runtime; an explicit setting by the user wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
