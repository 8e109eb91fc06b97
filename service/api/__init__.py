"""The HTTP service: FastAPI app (main.py), routes per resource (routes/), settings (core/config.py).

Generic over the pipeline registry: nothing here knows how a denoiser works. Importing this package
is cheap; `service.api.main` pulls in FastAPI.
"""
