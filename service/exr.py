"""OpenEXR frames and sequence folders in and out (shared FRAME_FORMAT.md).

A frame is one single-part scanline EXR whose channels are named `LAYER.CHANNEL`
(`color.R`, `normal.X`, `depth.Z`, ...), half or float, in any order. Two leniencies that real
renderers need: bare `R`, `G`, `B` channels are read as the `color` layer when no `color.*`
channel exists, and a layer may use the RGB names for XYZ channels (`normal.R` = `normal.X`, ...),
or any single name for a one-channel layer. A sequence is a folder of `.exr` files whose names sort
in frame order, with an optional `sequence.json` beside them.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import Imath
import numpy as np
import OpenEXR

from service.frame import LAYERS, Frame, FrameError

_FLOAT = Imath.PixelType(Imath.PixelType.FLOAT)  # what `read_layers` asks the decoder for, whatever the file holds
# Alternative channel names accepted per channel count, after the spec's own names.
_ALIASES: dict[int, tuple[tuple[str, ...], ...]] = {
    3: (("R", "G", "B"), ("X", "Y", "Z")),
    2: (("X", "Y"), ("R", "G"), ("U", "V")),
}


def read_channels(source: str | Path | bytes) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Raw channels of an EXR file or in-memory EXR bytes.

    Returns (channel name -> (H, W) array in the file's pixel type (float16/float32/uint32),
    header dict). Raises FrameError when the data is not a readable OpenEXR image.
    """
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    try:
        with OpenEXR.File(handle, separate_channels=True) as exr:
            header = dict(exr.header())
            channels = {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as err:  # the binding raises RuntimeError/TypeError/OSError on bad or truncated data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    return channels, header


def group_layers(channels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Group `LAYER.CHANNEL` channels into (H, W, C) arrays of the known layers, in spec order.

    Unknown layers are dropped. Raises FrameError naming a known layer whose channels do not match
    its spec (missing or extra channels, i.e. a wrong channel count).
    """
    by_layer: dict[str, dict[str, np.ndarray]] = {}
    for full, pixels in channels.items():
        layer, chan = _split_channel(full, channels)
        by_layer.setdefault(layer, {})[chan] = pixels
    layers: dict[str, np.ndarray] = {}
    for layer, chans in by_layer.items():
        spec = LAYERS.get(layer)
        if spec is None:
            continue
        chans = {c: p for c, p in chans.items() if c != "A"}  # an alpha channel is never data here
        names = _match_channel_names(layer, spec.channels, tuple(chans))
        layers[layer] = np.stack([chans[c] for c in names], axis=-1)
    return layers


def _split_channel(full: str, all_names: Iterable[str]) -> tuple[str, str]:
    """(layer, channel) of a channel name: `LAYER.CHANNEL`, or a bare R/G/B read as `color` when the
    file has no `color.*` channel."""
    layer, _, chan = full.rpartition(".")
    if not layer and full in ("R", "G", "B") and not any(c.startswith("color.") for c in all_names):
        return "color", full
    return layer, chan


@dataclass(frozen=True)
class ExrHeader:
    """What an EXR header tells without decoding pixels."""

    width: int  # pixels, of the data window
    height: int  # pixels, of the data window
    layers: frozenset[str]  # known layers present; `color` also when `colorA` and `colorB` are
    channels: tuple[str, ...] = ()  # every channel name in the file

    def channels_of(self, layers: Iterable[str]) -> tuple[str, ...]:
        """The channels to decode for `layers` (known layers; those absent are skipped): `colorA` and
        `colorB` too for `color` when the file has no color channels (the frame contract averages them)."""
        wanted = set(layers)
        if "color" in wanted and not any(_split_channel(c, self.channels)[0] == "color" for c in self.channels):
            wanted |= {"colorA", "colorB"}
        return tuple(c for c in self.channels if _split_channel(c, self.channels)[0] in wanted & set(LAYERS))


def read_header(source: str | Path | bytes) -> ExrHeader:
    """Size and layers of an EXR file or in-memory EXR bytes, from its header alone.

    Raises FrameError when the data is not a readable OpenEXR image."""
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    try:
        with OpenEXR.File(handle, header_only=True) as exr:  # the header dict empties when the file closes
            header = exr.header()
            names = [ch.name for ch in header["channels"]]
            low, high = header["dataWindow"]
    except Exception as err:  # the binding raises RuntimeError/TypeError/OSError/KeyError on bad data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    layers = {_split_channel(name, names)[0] for name in names} & set(LAYERS)
    if {"colorA", "colorB"} <= layers:
        layers.add("color")
    return ExrHeader(int(high[0] - low[0] + 1), int(high[1] - low[1] + 1), frozenset(layers), tuple(names))


def read_layers(source: str | Path | bytes, header: ExrHeader, layers: Iterable[str] = LAYERS) -> dict[str, np.ndarray]:
    """The known `layers` of an EXR file or bytes whose header is `header` (`read_header`), decoding only
    their channels (`ExrHeader.channels_of`): no other channel is ever converted or held in memory.

    Returns layer -> (H, W, C) float32 array in spec channel order (`group_layers`). Raises FrameError when
    the pixel data is unreadable (truncated, corrupt), a channel is subsampled, or a layer's channels do not
    match its spec (naming the layer).
    """
    names = header.channels_of(layers)
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    try:
        exr = OpenEXR.InputFile(handle)  # the binding's channel-selective reader
        try:
            data = exr.channels(list(names), _FLOAT) if names else []
        finally:
            exr.close()
    except Exception as err:  # the binding raises OSError/RuntimeError/TypeError on bad or truncated data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    pixels: dict[str, np.ndarray] = {}
    for name, raw in zip(names, data, strict=True):
        if len(raw) != 4 * header.width * header.height:
            layer = _split_channel(name, header.channels)[0]
            raise FrameError(f"channel '{name}' is subsampled; every channel must have one value per pixel", layer)
        pixels[name] = np.frombuffer(raw, np.float32).reshape(header.height, header.width)
    return group_layers(pixels)


def _match_channel_names(layer: str, expected: tuple[str, ...], present: tuple[str, ...]) -> tuple[str, ...]:
    if len(expected) == 1 and len(present) == 1:
        return present
    for names in (expected, *_ALIASES.get(len(expected), ())):
        if set(names) == set(present):
            return names
    raise FrameError(
        f"layer '{layer}' has {len(present)} channel(s) ({', '.join(sorted(present))}); "
        f"expected {len(expected)} ({' '.join(expected)})",
        layer,
    )


def read_frame(source: str | Path | bytes, *, repair: bool = True) -> Frame:
    """Read one frame (a path or in-memory EXR bytes) into a validated float32 Frame (known layers only)."""
    return Frame.from_buffers(read_layers(source, read_header(source)), repair=repair)


def encode_frame(buffers: Mapping[str, np.ndarray] | Frame, *, half: bool = False) -> bytes:
    """EXR bytes of `buffers` (layer -> (H, W, C) array), ZIP-compressed, float32 or half channels.

    Layers must be known layers of the frame format; channels are named from the spec.
    """
    sink = io.BytesIO()
    _write(sink, buffers, half)
    return sink.getvalue()


def write_frame(path: str | Path, buffers: Mapping[str, np.ndarray] | Frame, *, half: bool = False) -> None:
    """Write `buffers` as one EXR file at `path` (see `encode_frame`)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    _write(str(path), buffers, half)


def _write(target: str | io.BytesIO, buffers: Mapping[str, np.ndarray] | Frame, half: bool) -> None:
    if isinstance(buffers, Frame):
        buffers = buffers.buffers
    dtype = np.float16 if half else np.float32
    channels: dict[str, np.ndarray] = {}
    for layer, value in buffers.items():
        spec = LAYERS.get(layer)
        if spec is None:
            raise FrameError(f"cannot write unknown layer '{layer}'", layer)
        arr = np.asarray(value)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3 or arr.shape[2] != len(spec.channels):
            raise FrameError(f"layer '{layer}' has shape {arr.shape}; expected (H, W, {len(spec.channels)})", layer)
        with np.errstate(over="ignore"):
            for c, chan in enumerate(spec.channels):
                channels[f"{layer}.{chan}"] = np.ascontiguousarray(arr[:, :, c], dtype=dtype)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(target)


def list_sequence(folder: str | Path) -> list[Path]:
    """The `.exr` files of a sequence folder in frame order (sorted by name).

    Raises FrameError when the folder does not exist or holds no EXR file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FrameError(f"sequence folder '{folder}' does not exist")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".exr" and p.is_file())
    if not files:
        raise FrameError(f"sequence folder '{folder}' holds no .exr file")
    return files


def read_sequence(folder: str | Path) -> Iterator[tuple[Path, Frame]]:
    """Yield (path, frame) for every frame of a sequence folder, in order, reading lazily."""
    for path in list_sequence(folder):
        yield path, read_frame(path)


def read_metadata(folder: str | Path) -> dict[str, Any] | None:
    """The sequence's `sequence.json` (camera matrices, spp, ...) or None when absent."""
    path = Path(folder) / "sequence.json"
    return json.loads(path.read_text()) if path.is_file() else None
