"""mcdenoise serving side: frames, EXR I/O, classical stages, pipelines, ONNX runtime and HTTP API.

Imports neither torch nor mitsuba, and importing it changes no process state: the programs that run
kernels call `service.process.configure()` themselves.
"""
