"""Request bytes to a Frame and a denoised Frame to response bytes, with the service's limits.

Pure functions, run in the worker pool (they are CPU work): `decode` reads the EXR header first and
refuses a frame over the size limit before decoding any pixel (a few KiB of ZIP data can claim
gigabytes), then builds the Frame through the frame contract (`service.frame.Frame.from_buffers`).
"""

from __future__ import annotations

from dataclasses import dataclass

from service.api.core.errors import ApiError, InvalidExrError
from service.exr import encode_frame, group_layers, read_channels, read_header
from service.frame import Frame, FrameError
from service.preview import encode_png, tonemap

EXR = "image/x-exr"
PNG = "image/png"


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


def exr_size(body: bytes) -> tuple[int, int]:
    """(width, height) from the EXR header of `body`. Raises InvalidExrError when there is no EXR header."""
    try:
        header = read_header(body)
    except FrameError as err:
        raise InvalidExrError(f"body is not an OpenEXR image ({err.__cause__ or err})") from err
    return header.width, header.height


def check_size(width: int, height: int, max_width: int, max_height: int) -> None:
    """ApiError 413 when a frame of `width` x `height` pixels exceeds the service's limit (frames and sessions)."""
    if width > max_width or height > max_height:
        raise ApiError(413, "too_large", f"frame is {width}x{height}; this service takes at most "
                                         f"{max_width}x{max_height} (width x height)")


def decode(body: bytes, max_width: int, max_height: int) -> Frame:
    """The validated Frame in EXR `body`.

    Raises InvalidExrError (not EXR, truncated), ApiError 413 (larger than max_width x max_height) or
    FrameError naming the layer (missing or malformed layers, mismatched layer sizes).
    """
    check_size(*exr_size(body), max_width, max_height)
    try:
        channels, _ = read_channels(body)
    except FrameError as err:  # read_channels only raises on unreadable data
        raise InvalidExrError(f"body is a truncated or corrupt OpenEXR image ({err.__cause__ or err})") from err
    return Frame.from_buffers(group_layers(channels))


def encode(frame: Frame, output: Output) -> bytes:
    """Response bytes: EXR with the `color` layer (float32) or a PNG preview of it.

    frame: denoised Frame whose `color` is (H, W, 3) float32 linear radiance.
    """
    color = frame["color"]
    if output.media_type == PNG:
        return encode_png(tonemap(color, output.exposure))
    return encode_frame({"color": color})  # encode_frame writes float32 channels
