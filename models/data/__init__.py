"""Mitsuba 3 sequence renderer writing the frame format (see models/data/render.py), its scene library
and the bundled sample. Importing this package does not import mitsuba; the renderer modules do, lazily.
"""

from __future__ import annotations

from pathlib import Path

SAMPLES_ROOT = Path(__file__).resolve().parent / "samples"
# Bundled rendered sequences (120x120, 8 frames, 4 spp, 1024-spp reference, float16 channels; all together
# under 5 MB), the first one being the demo's (Makefile SAMPLE).
SAMPLE_DIRS: tuple[Path, ...] = (SAMPLES_ROOT / "shadows",)
