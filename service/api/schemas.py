"""JSON bodies of the API (pydantic models; they also document the API in /docs)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from service import pipelines


class ErrorBody(BaseModel):
    """Every 4xx/5xx answer; the WebSocket stream sends the same plus `frame`."""

    code: str = Field(description="stable machine-readable code, e.g. invalid_frame, busy")
    message: str = Field(description="what is wrong, naming the layer when one is at fault")
    layer: str | None = Field(None, description="the offending layer, when there is one")
    option: str | None = Field(None, description="the offending pipeline option, when there is one")


class PipelineInfo(BaseModel):
    name: str
    summary: str
    requires: list[str] = Field(description="layers a frame must have")
    optional: list[str] = Field(description="layers used when present")
    temporal: bool = Field(description="whether the output depends on earlier frames of the sequence")
    options: dict[str, Any] = Field(description="option names with their defaults")
    option_specs: dict[str, dict[str, Any]] = Field(
        description="per option: type, default, bounds (minimum, maximum, exclusiveMinimum, exclusiveMaximum), "
                    "odd, enum, nullable, and `allowed` in words; values outside answer 400 invalid_options")


class PipelineList(BaseModel):
    default: str
    pipelines: list[PipelineInfo]


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    pipeline: str = Field(pipelines.DEFAULT, max_length=64, description="a name from GET /v1/pipelines")
    width: int = Field(gt=0, description="frame width of the sequence, pixels")
    height: int = Field(gt=0, description="frame height of the sequence, pixels")
    options: dict[str, Any] = Field(default_factory=dict, description="pipeline options (see GET /v1/pipelines)")
    online: bool = Field(False, description="fine-tune online while streaming (pipelines with an `online` option)")
    channel_map: dict[str, Any] | None = Field(
        None, description='how the frames\' channels make layers: {"layers": {LAYER: {"channels": [...], "scale": '
                          '[...], "add": [...], "clip": [lo, hi], "replace_zero": v}}} (README, frame format); '
                          "default: the service's MCDENOISE_CHANNEL_MAP, else the file's recognised dialect")
    view_layer: str | None = Field(None, max_length=256, description="the Blender view layer to read from files with "
                                                                     "several")


class SessionInfo(BaseModel):
    id: str = Field(description="unguessable session id")
    pipeline: str
    width: int
    height: int
    options: dict[str, Any] = Field(description="all pipeline options in effect")
    online: bool
    temporal: bool
    frames: int = Field(description="frames denoised")
    errors: int = Field(description="frames refused or failed; the session went on")
    mean_ms: float | None = Field(description="mean time of the pipeline step per frame, ms")
    p95_ms: float | None = Field(description="95th percentile of the step time over the last 1000 frames, ms")
    created_at: float = Field(description="unix time, seconds")
    idle_s: float
    expires_in_s: float = Field(description="seconds until the session ends unless used")
    online_status: dict[str, Any] | None = Field(description="state of the online-training worker, if any")
