"""mcdenoise serving side: frames, EXR I/O, classical stages, pipelines, ONNX runtime and HTTP API.

Imports neither torch nor mitsuba."""
