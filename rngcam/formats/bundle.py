"""The HDF5 capture bundle (schema v1): one import for its public names.

The layout and the records are in `bundle_schema`, the atomic write in `bundle_write`, the
opener every command shares in `bundle_read`, and what `rngcam inspect` shows in
`bundle_summary`.
"""

from rngcam.formats.bundle_read import (
    bundle_checksum,
    check_bundle_path,
    open_bundle,
    open_checked,
    read_bundle,
    read_bundle_with_warnings,
    validate_bundle,
)
from rngcam.formats.bundle_schema import (
    COMPRESSIONS,
    FORMAT_NAME,
    SCHEMA_VERSION,
    WARNING_PREFIX,
    Bundle,
    Calibration,
    CameraRecord,
    TriggerRecord,
    Truth,
    camera_channels,
    check_bundle,
    is_warning,
    trigger_faults,
)
from rngcam.formats.bundle_summary import inspect_bundle, render_summary, summarise, summary_dict
from rngcam.formats.bundle_write import write_bundle

__all__ = [
    "COMPRESSIONS", "FORMAT_NAME", "SCHEMA_VERSION", "WARNING_PREFIX", "Bundle", "Calibration",
    "CameraRecord", "TriggerRecord", "Truth", "bundle_checksum", "camera_channels", "check_bundle_path", "check_bundle",
    "inspect_bundle", "is_warning", "open_bundle", "open_checked", "read_bundle",
    "read_bundle_with_warnings", "render_summary", "summarise", "summary_dict", "trigger_faults",
    "validate_bundle", "write_bundle",
]
