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


RENDER_PARTS = ("first", "second")  # the part names of two renders of a frame in one file (`join_renders`)
_WINDOWS = ("dataWindow", "displayWindow")  # where the pixels lie: kept when a file is written again
_WRITTEN = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}  # how we write a file


@dataclass(frozen=True)
class ExrHeader:
    """What an EXR header tells without decoding pixels."""

    width: int  # pixels, of the data window
    height: int  # pixels, of the data window
    layers: frozenset[str]  # known layers present; `color` also when `colorA` and `colorB` are
    channels: tuple[str, ...] = ()  # every channel name in the file (of its first part)
    mapping: ChannelMap = field(default_factory=lambda: ChannelMap("mcdenoise"))  # how channels make layers
    second: ChannelMap | None = None  # a second render in part `second` (`join_renders`): the halves' colorB
    second_channels: tuple[str, ...] = ()  # every channel name of that part

    def wanted(self, layers: Iterable[str]) -> set[str]:
        """The layers to assemble for `layers`: `colorA` and `colorB` too for `color` when the file has no
        color channels (the frame contract averages them); with a second render, the first render's
        `color` for any of the three."""
        wanted = set(layers)
        if "color" in wanted and "color" not in self.mapping.layers:
            wanted |= {"colorA", "colorB"}
        if self.second is not None and wanted & {"color", "colorA", "colorB"}:
            wanted.add("color")
        return wanted

    def channels_of(self, layers: Iterable[str]) -> tuple[str, ...]:
        """The channels of the first part to decode for `layers` (`wanted`; those absent are skipped)."""
        wanted = self.wanted(layers)
        needed = {c for name, src in self.mapping.layers.items() if name in wanted for c in src.file_channels()}
        return tuple(c for c in self.channels if c in needed)


def read_header(source: str | Path | bytes, channel_map: ChannelMap | None = None,
                view_layer: str | None = None) -> ExrHeader:
    """Size, layers and dialect of an EXR file or in-memory EXR bytes, from its header alone
    (`service.dialects.detect`, with the user's `channel_map` and Blender `view_layer` when given). A file
    of exactly two parts named `first` and `second` (`join_renders`) holds two renders of the frame: the
    colour of the second is the halves' `colorB`. Of any other multi-part file the first part is read.

    Raises FrameError when the data is not a readable OpenEXR image, or its second render has another size
    or no colour (naming `colorB`); DialectError when a channel map names channels the file lacks, or for
    a Blender file with several view layers and none named."""
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    try:
        with OpenEXR.File(handle, header_only=True) as exr:  # the header dict empties when the file closes
            header = exr.header()
            names = [ch.name for ch in header["channels"]]
            window = tuple(tuple(int(v) for v in corner) for corner in header["dataWindow"])
            second: tuple[list[str], tuple] | None = None
            if len(exr.parts) == 2 and tuple(part.name() for part in exr.parts) == RENDER_PARTS:
                other = exr.parts[1].header
                second = ([ch.name for ch in other["channels"]],
                          tuple(tuple(int(v) for v in corner) for corner in other["dataWindow"]))
    except Exception as err:  # the binding raises RuntimeError/TypeError/OSError/KeyError on bad data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    (x0, y0), (x1, y1) = window
    width, height = x1 - x0 + 1, y1 - y0 + 1
    mapping = detect(names, channel_map=channel_map, view_layer=view_layer)
    _check_channels(what, mapping, names, mapping.layers)
    second_map, second_names = None, ()
    if second is not None:
        second_names, second_window = tuple(second[0]), second[1]
        if second_window != window:
            (u0, v0), (u1, v1) = second_window
            raise FrameError(f"{what}: its second render is {u1 - u0 + 1}x{v1 - v0 + 1} but the first is "
                             f"{width}x{height}", "colorB")
        second_map = detect(second_names, channel_map=channel_map, view_layer=view_layer)
        if "color" not in second_map.layers or "color" not in mapping.layers:
            raise FrameError(f"{what}: both renders need a colour (layer 'color' in their dialect)", "colorB")
        _check_channels(what, second_map, second_names, ("color",))
    layers = set(mapping.layers) | ({"colorA", "colorB"} if second_map is not None else set())
    if {"colorA", "colorB"} <= layers:
        layers.add("color")
    return ExrHeader(width, height, frozenset(layers), tuple(names), mapping, second_map, second_names)


def _check_channels(what: str, mapping: ChannelMap, names: Iterable[str], layers: Iterable[str]) -> None:
    """DialectError naming the first of `layers` whose channels in `mapping` are not all among `names`."""
    missing = mapping.missing_channels(names)
    for layer in layers:
        if layer in missing:
            raise DialectError(f"{what}: the channel map's layer '{layer}' names channels the file lacks: "
                               f"{', '.join(missing[layer])}", layer)


def read_layers(source: str | Path | bytes, header: ExrHeader, layers: Iterable[str] = LAYERS) -> dict[str, np.ndarray]:
    """The known `layers` of an EXR file or bytes whose header is `header` (`read_header`), decoding only
    their channels (`ExrHeader.channels_of`): no other channel of a single-part file is ever converted or
    held in memory (a file of two renders is decoded whole, once, for the second render's colour).

    Returns layer -> (H, W, C) float32 array in spec channel order (the header's `mapping`). Raises FrameError
    when the pixel data is unreadable (truncated, corrupt), a channel is subsampled, or a layer's channels do
    not match its spec (naming the layer).
    """
    names = header.channels_of(layers)
    what = "data" if isinstance(source, bytes | bytearray) else f"file '{source}'"
    handle = io.BytesIO(source) if isinstance(source, bytes | bytearray) else str(source)
    second = None
    try:
        if header.second is None:
            exr = OpenEXR.InputFile(handle)  # the binding's channel-selective reader
            try:
                data = exr.channels(list(names), _FLOAT) if names else []
            finally:
                exr.close()
            pixels = {name: np.frombuffer(raw, np.float32) for name, raw in zip(names, data, strict=True)}
        else:
            with OpenEXR.File(handle, separate_channels=True) as exr:  # every part, decoded once
                first, other = (part.channels for part in exr.parts)
                pixels = {name: np.asarray(first[name].pixels, np.float32).ravel() for name in names}
                colour = header.second.layers["color"].file_channels()
                second = {name: np.asarray(other[name].pixels, np.float32).ravel() for name in colour}
    except Exception as err:  # the binding raises OSError/RuntimeError/TypeError on bad or truncated data
        raise FrameError(f"{what} is not a readable OpenEXR image ({err})") from err
    pixels = {name: _full_size(name, values, header, header.mapping) for name, values in pixels.items()}
    wanted = header.wanted(layers)
    out = {layer: src.assemble(pixels, layer) for layer, src in header.mapping.layers.items()
           if layer in wanted and layer in LAYERS}
    if second is not None and "color" in out:
        out["colorA"] = out.pop("color")  # the Frame's `color` becomes the mean of the two renders
        second = {name: _full_size(name, values, header, header.second) for name, values in second.items()}
        out["colorB"] = header.second.layers["color"].assemble(second, "colorB")
    return out


def _full_size(name: str, values: np.ndarray, header: ExrHeader, mapping: ChannelMap) -> np.ndarray:
    """Channel `name`'s decoded values (flat float32) as (H, W); FrameError naming its layer when it holds
    fewer values (a subsampled channel)."""
    if values.size != header.width * header.height:
        layer = "colorB" if mapping is header.second else next(
            (k for k, src in mapping.layers.items() if name in src.file_channels()), None)
        raise FrameError(f"channel '{name}' is subsampled; every channel must have one value per pixel", layer)
    return values.reshape(header.height, header.width)


def _kept_attributes(header: Mapping[str, Any]) -> dict[str, Any]:
    """What a file written from another keeps of its header: the string attributes (Blender's
    `BlenderMultiChannel`, ...) but the part name, and where its pixels lie (`_WINDOWS`)."""
    return {k: v for k, v in header.items() if (isinstance(v, str) and k != "name") or k in _WINDOWS}


def join_renders(first: str | Path | bytes, second: str | Path | bytes) -> bytes:
    """One EXR of two renders of a frame with different seeds (files or bytes, any dialect): part `first`
    every channel of `first` (`_kept_attributes` of its header), part `second` the colour channels of
    `second` in its dialect (all of them when it has none that the reader recognises), in the same windows.
    Read back, the second render's colour is the halves' `colorB` (`read_header`). FrameError when the
    sizes differ."""
    channels, header = read_channels(first)
    other, other_header = read_channels(second)
    (h0, w0), (h1, w1) = (next(iter(c.values())).shape for c in (channels, other))
    if (h0, w0) != (h1, w1):
        raise FrameError(f"the second render is {w1}x{h1} but the first is {w0}x{h0}", "colorB")
    colour = detect(other).layers.get("color")
    if colour is not None and not colour.error:
        other = {name: other[name] for name in colour.file_channels()}
    kept = _kept_attributes(header)
    second_kept = {**_kept_attributes(other_header), **{k: v for k, v in kept.items() if k in _WINDOWS}}
    parts = [OpenEXR.Part({**kept, **_WRITTEN}, channels, name=RENDER_PARTS[0]),
             OpenEXR.Part({**second_kept, **_WRITTEN}, other, name=RENDER_PARTS[1])]
    sink = io.BytesIO()
    with OpenEXR.File(parts) as exr:
        exr.write(sink)
    return sink.getvalue()


def write_with_input(path: str | Path, source: str | Path, color: np.ndarray, mapping: ChannelMap) -> None:
    """Write the EXR file `source`'s channels (their pixel types, and `_kept_attributes` of its header) plus
    `color` ((H, W, 3) float32) as the channels `mapping.result` names (Blender: a `Denoised` pass of the view
    layer read), to `path`."""
    channels, header = read_channels(source)
    channels.update({name: np.ascontiguousarray(color[..., c], np.float32) for c, name in enumerate(mapping.result)})
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File({**_kept_attributes(header), **_WRITTEN}, channels) as exr:
        exr.write(str(path))


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
    with OpenEXR.File(dict(_WRITTEN), channels) as exr:
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


def paired_sequence(folder: str | Path, second: str | Path | None = None) -> list[tuple[Path, Path | None]]:
    """The frames of a sequence folder (`list_sequence`), each with frame i of `second`, a folder of a
    second render of the same frames, or None. FrameError when the two hold different counts."""
    paths = list_sequence(folder)
    if second is None:
        return [(path, None) for path in paths]
    seconds = list_sequence(second)
    if len(seconds) != len(paths):
        raise FrameError(f"the second render '{second}' has {len(seconds)} frames; '{folder}' has {len(paths)}")
    return list(zip(paths, seconds, strict=True))


def read_sequence(folder: str | Path, channel_map: ChannelMap | None = None,
                  view_layer: str | None = None) -> Iterator[tuple[Path, Frame]]:
    """Yield (path, frame) for every frame of a sequence folder, in order, reading lazily."""
    for path in list_sequence(folder):
        yield path, read_frame(path, channel_map=channel_map, view_layer=view_layer)


def read_metadata(folder: str | Path) -> dict[str, Any] | None:
    """The sequence's `sequence.json` (camera matrices, spp, ...) or None when absent."""
    path = Path(folder) / "sequence.json"
    return json.loads(path.read_text()) if path.is_file() else None
