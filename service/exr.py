"""OpenEXR frames and sequence folders in and out (shared FRAME_FORMAT.md).

A frame is one single-part scanline EXR, half or float channels in any order. Which channels make which
layer is the file's dialect (`service.dialects`): the frame format's own `LAYER.CHANNEL` names
(`color.R`, `normal.X`, `depth.Z`, ...), Blender's multilayer EXR, Mitsuba's AOVs, or a user's channel
map. Frames are written in the frame format. A sequence is a folder of `.exr` files whose names sort in
frame order, with an optional `sequence.json` beside them.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import Imath
import numpy as np
import OpenEXR

from service.dialects import ChannelMap, DialectError, detect
from service.frame import LAYERS, Frame, FrameError

_FLOAT = Imath.PixelType(Imath.PixelType.FLOAT)  # what `read_layers` asks the decoder for, whatever the file holds


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


@dataclass(frozen=True)
class ExrHeader:
    """What an EXR header tells without decoding pixels."""

    width: int  # pixels, of the data window
    height: int  # pixels, of the data window
    layers: frozenset[str]  # known layers present; `color` also when `colorA` and `colorB` are
    channels: tuple[str, ...] = ()  # every channel name in the file
    mapping: ChannelMap = field(default_factory=lambda: ChannelMap("mcdenoise"))  # how channels make layers
    second: ChannelMap | None = None  # a second part with a `color`: a second render, the halves' colorB

    def channels_of(self, layers: Iterable[str]) -> tuple[str, ...]:
        """The channels to decode for `layers` (known layers; those absent are skipped): `colorA` and
        `colorB` too for `color` when the file has no color channels (the frame contract averages them)."""
        wanted = set(layers)
        if "color" in wanted and "color" not in self.mapping.layers:
            wanted |= {"colorA", "colorB"}
        needed = {c for name, src in self.mapping.layers.items() if name in wanted for c in src.file_channels()}
        return tuple(c for c in self.channels if c in needed)


def read_header(source: str | Path | bytes, channel_map: ChannelMap | None = None,
                view_layer: str | None = None) -> ExrHeader:
    """Size, layers and dialect of an EXR file or in-memory EXR bytes, from its header alone
    (`service.dialects.detect`, with the user's `channel_map` and Blender `view_layer` when given).

    Raises FrameError when the data is not a readable OpenEXR image, when a channel map names channels
    the file lacks, or for a Blender file with several view layers and none named."""
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    try:
        with OpenEXR.File(handle, header_only=True) as exr:  # the header dict empties when the file closes
            header = exr.header()
            names = [ch.name for ch in header["channels"]]
            low, high = header["dataWindow"]
            parts = [(names, {k: v for k, v in header.items() if k == "BlenderMultiChannel"})]
            if len(exr.parts) > 1:  # a second render (`join_renders`)
                second = exr.parts[1].header
                parts.append(([ch.name for ch in second["channels"]],
                              {k: v for k, v in second.items() if k == "BlenderMultiChannel"}))
    except Exception as err:  # the binding raises RuntimeError/TypeError/OSError/KeyError on bad data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    mapping = _part_mapping(what, parts[0], channel_map, view_layer)
    second_map = _part_mapping(what, parts[1], channel_map, view_layer) if len(parts) > 1 else None
    layers = set(mapping.layers)
    if second_map is not None and "color" in second_map.layers and "color" in layers:
        layers |= {"colorA", "colorB"}
    else:
        second_map = None
    if {"colorA", "colorB"} <= layers:
        layers.add("color")
    return ExrHeader(int(high[0] - low[0] + 1), int(high[1] - low[1] + 1), frozenset(layers), tuple(names), mapping,
                     second_map)


def _part_mapping(what: str, part: tuple[list[str], dict[str, Any]], channel_map: ChannelMap | None,
                  view_layer: str | None) -> ChannelMap:
    """The dialect of one part's channel names and attributes; DialectError when a channel map names
    channels the part lacks."""
    names, attributes = part
    mapping = detect(names, attributes, channel_map=channel_map, view_layer=view_layer)
    missing = mapping.missing_channels(names)
    if missing:
        layer, channels = next(iter(missing.items()))
        raise DialectError(f"{what}: the channel map's layer '{layer}' names channels the file lacks: "
                           f"{', '.join(channels)}", layer)
    return mapping


def read_layers(source: str | Path | bytes, header: ExrHeader, layers: Iterable[str] = LAYERS) -> dict[str, np.ndarray]:
    """The known `layers` of an EXR file or bytes whose header is `header` (`read_header`), decoding only
    their channels (`ExrHeader.channels_of`): no other channel is ever converted or held in memory.

    Returns layer -> (H, W, C) float32 array in spec channel order (the header's `mapping`). Raises FrameError when
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
            layer = next((k for k, src in header.mapping.layers.items() if name in src.file_channels()), None)
            raise FrameError(f"channel '{name}' is subsampled; every channel must have one value per pixel", layer)
        pixels[name] = np.frombuffer(raw, np.float32).reshape(header.height, header.width)
    wanted = set(layers) | ({"colorA", "colorB"} if "color" in layers else set())
    out = {layer: src.assemble(pixels, layer) for layer, src in header.mapping.layers.items()
           if layer in wanted and layer in LAYERS}
    if header.second is not None and wanted & {"color", "colorA", "colorB"}:
        out["colorA"] = out.pop("color")  # the Frame's `color` becomes the mean of the two renders
        out["colorB"] = _second_color(source, header.second, what)
    return out


def _second_color(source: str | Path | bytes, mapping: ChannelMap, what: str) -> np.ndarray:
    """The `color` of a file's second part, (H, W, 3) float32, in that part's dialect `mapping`."""
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    try:
        with OpenEXR.File(handle, separate_channels=True) as exr:
            channels = exr.parts[1].channels
            pixels = {name: np.asarray(channels[name].pixels, np.float32) for name in mapping.layers["color"].channels}
    except Exception as err:  # the binding raises OSError/RuntimeError/TypeError on bad or truncated data
        raise FrameError(f"{what}: its second part is not readable ({err})") from err
    return mapping.layers["color"].assemble(pixels, "colorB")


def join_renders(first: str | Path | bytes, second: str | Path | bytes) -> bytes:
    """One two-part EXR of two renders of a frame with different seeds (files or bytes, any dialect):
    part 0 every channel of `first`, part 1 those of `second`, their string attributes kept. Read back,
    part 0 is the frame and part 1's `color` its second half (`read_header`: `colorA`, `colorB`)."""
    parts = []
    for index, render in enumerate((first, second)):
        channels, header = read_channels(render)
        attributes = {k: v for k, v in header.items() if isinstance(v, str) and k != "name"}
        parts.append(OpenEXR.Part({**attributes, "compression": OpenEXR.ZIP_COMPRESSION,
                                   "type": OpenEXR.scanlineimage}, channels, name=("first", "second")[index]))
    sink = io.BytesIO()
    with OpenEXR.File(parts) as exr:
        exr.write(sink)
    return sink.getvalue()


def read_frame(source: str | Path | bytes, *, repair: bool = True, channel_map: ChannelMap | None = None,
               view_layer: str | None = None) -> Frame:
    """Read one frame (a path or in-memory EXR bytes) into a validated float32 Frame (known layers only),
    in its dialect (`read_header`)."""
    header = read_header(source, channel_map, view_layer)
    return Frame.from_buffers(read_layers(source, header), repair=repair)


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


def write_with_input(path: str | Path, source: str | Path, color: np.ndarray, mapping: ChannelMap) -> None:
    """Write the EXR file `source`'s channels (their pixel types and its string attributes, such as
    Blender's `BlenderMultiChannel`, kept) plus `color` ((H, W, 3) float32) as the channels
    `mapping.result` names (Blender: a `Denoised` pass of the view layer read), to `path`."""
    channels, header = read_channels(source)
    channels.update({name: np.ascontiguousarray(color[..., c], np.float32) for c, name in enumerate(mapping.result)})
    attributes = {k: v for k, v in header.items() if isinstance(v, str)}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File({**attributes, "compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      channels) as exr:
        exr.write(str(path))


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


def read_sequence(folder: str | Path, channel_map: ChannelMap | None = None,
                  view_layer: str | None = None) -> Iterator[tuple[Path, Frame]]:
    """Yield (path, frame) for every frame of a sequence folder, in order, reading lazily."""
    for path in list_sequence(folder):
        yield path, read_frame(path, channel_map=channel_map, view_layer=view_layer)


def read_metadata(folder: str | Path) -> dict[str, Any] | None:
    """The sequence's `sequence.json` (camera matrices, spp, ...) or None when absent."""
    path = Path(folder) / "sequence.json"
    return json.loads(path.read_text()) if path.is_file() else None
