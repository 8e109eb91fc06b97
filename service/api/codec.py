"""Request bytes to a Frame and a denoised Frame to response bytes, with the service's limits.

Pure functions, run in the worker pool (they are CPU work): `decode` reads the EXR header first and
refuses a frame over the size limit or the memory budget before decoding any pixel (a few KiB of ZIP data
can claim gigabytes), decodes only the channels of the layers the pipeline reads, then builds the Frame
through the frame contract (`service.frame.Frame.from_buffers`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from service.api.core.config import Settings
from service.api.core.errors import ApiError, InvalidExrError
from service.dialects import ChannelMap, DialectError
from service.exr import ExrHeader, encode_frame, read_header, read_layers
from service.frame import OUTPUT_LAYERS, Frame, FrameError
from service.preview import encode_png, tonemap

EXR = "image/x-exr"
PNG = "image/png"
# Peak memory of one frame per decoded float32 channel value: the decoder's buffer, the stacked layer, the
# repaired/emission-free copies, and the pipeline's own work. Measured peak RSS over the decoded bytes,
# 768x768, 1 thread: crossreg 6.5 (the U-Net's activations), svgf 2.3, crossregression 2.0, others less.
MEMORY_FACTOR = 8


@dataclass(frozen=True)
class Output:
    """What a client asked to get back."""

    media_type: str = EXR  # EXR (the `color` layer, float32) or PNG (tone-mapped 8-bit preview)
    exposure: float = 1.0  # multiplies radiance before the PNG tone map; unused for EXR


def media_type_of(content_type: str | None) -> str:
    """The bare media type of a Content-Type header value, lower case ('' when absent)."""
    return (content_type or "").split(";")[0].strip().lower()


def choose_output(accept: str | None, exposure: float = 1.0) -> Output:
    """EXR unless the Accept header prefers image/png (by q-value; ties go to EXR)."""
    quality: dict[str, float] = {}
    for part in (accept or "").split(","):
        kind, *params = (p.strip() for p in part.split(";"))
        q = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        quality[kind.lower()] = max(q, quality.get(kind.lower(), 0.0))
    png = quality.get(PNG, 0.0)
    if png > 0.0 and png > quality.get(EXR, 0.0):
        return Output(PNG, exposure)
    return Output(EXR, exposure)


def exr_header(body: bytes, channel_map: ChannelMap | None = None, view_layer: str | None = None) -> ExrHeader:
    """The EXR header of `body`, in its dialect (`service.exr.read_header`). Raises InvalidExrError when
    there is no EXR header, DialectError (a FrameError) when its channels cannot be read as asked."""
    try:
        return read_header(body, channel_map, view_layer)
    except DialectError:
        raise
    except FrameError as err:
        raise InvalidExrError(f"body is not an OpenEXR image ({err.__cause__ or err})") from err


def check_size(width: int, height: int, max_width: int, max_height: int) -> None:
    """ApiError 413 when a frame of `width` x `height` pixels exceeds the service's limit (frames and sessions)."""
    if width > max_width or height > max_height:
        raise ApiError(413, "too_large", f"frame is {width}x{height}; this service takes at most "
                                         f"{max_width}x{max_height} (width x height)")


def check_memory(header: ExrHeader, channels: int, max_frame_mb: int) -> None:
    """ApiError 413 when a frame's memory estimate (W x H x `channels` decoded x 4 bytes x MEMORY_FACTOR)
    exceeds the per-frame budget of `max_frame_mb` MiB."""
    estimate = header.width * header.height * channels * 4 * MEMORY_FACTOR
    if estimate > max_frame_mb * 2**20:
        raise ApiError(413, "too_large", f"frame of {header.width}x{header.height} pixels with {channels} channels "
                                         f"to decode needs about {estimate / 2**20:.0f} MiB; this service allows "
                                         f"{max_frame_mb} MiB per frame (MCDENOISE_MAX_FRAME_MB)")


def decode(body: bytes, settings: Settings, layers: Iterable[str], channel_map: ChannelMap | None = None,
           view_layer: str | None = None) -> Frame:
    """The validated Frame in EXR `body`, with the known `layers` it has (every other channel is skipped),
    read in its dialect: `channel_map` and `view_layer` (a session's), else the service's settings.

    Raises InvalidExrError (not EXR, truncated), ApiError 413 (larger than the size limits, or over the
    per-frame memory budget, both from the header before any pixel is decoded) or FrameError naming the
    layer (missing or malformed layers, mismatched layer sizes, values beyond the layer's limit).
    """
    header = exr_header(body, channel_map or settings.default_channel_map, view_layer or settings.view_layer or None)
    check_size(header.width, header.height, settings.max_width, settings.max_height)
    if header.second is None:
        decoded = len(header.channels_of(layers))
    else:  # a file of two renders is decoded whole
        decoded = len(header.channels) + len(header.second_channels)
    check_memory(header, decoded, settings.max_frame_mb)
    try:
        buffers = read_layers(body, header, layers)
    except FrameError as err:
        if err.layer is not None:  # a layer's channels do not match its spec: the frame's fault, named
            raise
        raise InvalidExrError(f"body is a truncated or corrupt OpenEXR image ({err.__cause__ or err})") from err
    return Frame.from_buffers(buffers)


def encode(frame: Frame, output: Output) -> bytes:
    """Response bytes: EXR with the `color` layer and, from a pipeline that estimates it, `error` (float32),
    or a PNG preview of `color`.

    frame: denoised Frame whose `color` is (H, W, 3) float32 linear radiance.
    """
    color = frame["color"]
    if output.media_type == PNG:
        return encode_png(tonemap(color, output.exposure))
    return encode_frame({k: frame[k] for k in OUTPUT_LAYERS if k in frame})  # encode_frame writes float32
