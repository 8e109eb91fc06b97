"""mcdenoise serving side: frames, EXR I/O, classical stages, pipelines, ONNX runtime and HTTP API.

Imports neither torch nor mitsuba. Importing it applies `service.process.configure()` (OpenMP waiting,
a numba cache folder per version of the kernels, malloc keeping frame buffers), before any kernel loads.
"""

from service.process import configure

configure()
