"""metrics.json's schema: the type of every field a reader of a result folder uses.

The writer (`Result.save`) and the readers (`report`, `inspect`, resume, the sweep's trial cache)
share it: a folder from someone else whose metrics.json holds a field of another type is refused
in one line (`check_metrics`) instead of failing somewhere in the page. Fields not named here are
kept as they are (shown as text, never computed with).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StrictStr, ValidationError

Number = StrictInt | StrictFloat  # JSON's numbers; NaN and Infinity as Python's json writes them
Count = Annotated[StrictInt, Field(ge=0)]
Text = Annotated[StrictStr, Field(max_length=100_000)]
Lines = Annotated[list[Text], Field(max_length=10_000)]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)


class LeftOut(_Open):
    """A part of the method left out of a run, and why."""

    component: Text
    reason: Text


class Misfit(_Open):
    """The misfit verdict: its line is shown."""

    line: Text | None = None


class Metrics(_Open):
    """The fields of metrics.json that rngcam reads back (all optional: older runs lack some)."""

    method: Text | None = None
    status: Text | None = None
    ended_by: Text | None = None
    device: Text | None = None
    seconds: Number | None = None
    wall_seconds: Number | None = None
    setup_seconds: Number | None = None
    iterations: Count | None = None
    peak_rss_bytes: Number | None = None
    frames: Count | None = None
    height: Count | None = None
    width: Count | None = None
    channels: Count | None = None
    threads: Count | Text | None = None
    fps: Number | None = None
    psnr_db: Number | None = None
    psnr_intermediate_db: Number | None = None
    psnr_dynamic_db: Number | None = None
    ssim: Number | None = None
    ssim_intermediate: Number | None = None
    residual_rs: Number | None = None
    residual_gs: Number | None = None
    centroid_error_median_px: Number | None = None
    centroid_error_p90_px: Number | None = None
    ghost_median: Number | None = None
    ghost_max: Number | None = None
    heldout: Number | None = None
    left_out: Annotated[list[LeftOut], Field(max_length=1_000)] = []
    events: Lines = []
    warnings: Lines = []
    notes: Lines = []
    error_visibility_caveats: Lines = []
    error_visibility: dict[Text, Number | None] = {}
    masked_fraction: dict[Text, Number | None] = {}
    misfit: Misfit | None = None
    above_noise: Misfit | None = None  # a run stopped above the noise level without a verdict: its line
    method_results: dict | None = None
    settings: dict = {}
    resumed: StrictBool | None = None


def check_metrics(value: object, where: str) -> dict:
    """`value` (parsed metrics.json) as a dict whose named fields have their types; ValueError
    with one line naming `where`, the first field that is off and why, otherwise."""
    if not isinstance(value, dict):
        raise ValueError(f"{where} holds a JSON {type(value).__name__}, expected an object")
    try:
        Metrics.model_validate(value)
    except ValidationError as exc:
        err = exc.errors()[0]
        path = _path_in(value, err["loc"])
        got = value
        for part in path:
            got = got[part]
        field = ".".join(str(p) for p in path) or "(top)"
        raise ValueError(f"{where}: field '{field[:80]}' is of the wrong type or value "
                         f"(a {type(got).__name__}: {err['msg'][:120].lower()})") from None
    return value


def _path_in(value, loc: tuple) -> list:
    """The part of a pydantic error's location that names keys and indices of `value` (the
    rest names a union's member types)."""
    out = []
    for part in loc:
        if isinstance(value, dict) and part in value:
            value = value[part]
        elif isinstance(value, list) and isinstance(part, int) and 0 <= part < len(value):
            value = value[part]
        else:
            break
        out.append(part)
    return out
