"""GenICam feature handling shared by the backends (rngcam.acquire.features), on a node map
modelled on a Basler ace USB: TriggerMode per TriggerSelector (FrameBurstStart and FrameStart),
a writable ShutterMode, SFNC names; and the ace GigE / Aravis-fake names (ExposureTimeAbs, GainRaw)."""

from __future__ import annotations

import pytest

from rngcam.acquire.camera import CameraSettings
from rngcam.acquire.features import FeatureMap, apply_settings
from rngcam.errors import HardwareError


class NodeMap(FeatureMap):
    """Features as a dict; `per_selector` features hold one value per TriggerSelector entry."""

    def __init__(self, values: dict, enums: dict, read_only=(), per_selector=("TriggerMode", "TriggerSource")):
        self.values, self.enums, self.read_only = dict(values), enums, set(read_only)
        selectors = enums.get("TriggerSelector", ["FrameStart"])
        self.per = {}
        for name in per_selector:
            if name in self.values:
                value = self.values.pop(name)
                self.per[name] = dict.fromkeys(selectors, value)
        self.writes = []

    def readable(self, name):
        return name in self.values or name in self.per

    def writable(self, name):
        return self.readable(name) and name not in self.read_only

    def get(self, name):
        if name in self.per:
            return self.per[name][self.values.get("TriggerSelector", "FrameStart")]
        return self.values[name]

    def set(self, name, value):
        if name in self.enums and value not in self.enums[name]:
            raise ValueError(f"{name} has no entry {value}")
        self.writes.append((name, value))
        if name in self.per:
            self.per[name][self.values.get("TriggerSelector", "FrameStart")] = value
        else:
            self.values[name] = value

    def execute(self, name):
        pass

    def entries(self, name):
        return self.enums.get(name)


def ace_usb(**changes) -> NodeMap:
    values = {"TriggerSelector": "FrameStart", "TriggerMode": "On", "TriggerSource": "Line1",
              "TriggerActivation": "RisingEdge", "ExposureTime": 1000.0, "Gain": 0.0, "PixelFormat": "BayerRG12",
              "Width": 5472, "Height": 3648, "OffsetX": 0, "OffsetY": 0, "ShutterMode": "Global",
              "ExposureAuto": "Off", "GainAuto": "Off"}
    enums = {"TriggerSelector": ["FrameBurstStart", "FrameStart"], "ShutterMode": ["Global", "Rolling", "GlobalResetRelease"],
             "TriggerSource": ["Line1", "Software"], "TriggerMode": ["On", "Off"]}
    read_only = changes.pop("read_only", ())
    for k, v in changes.items():
        if v is None:
            values.pop(k, None)
            enums.pop(k, None)
        else:
            values[k] = v
    return NodeMap(values, enums, read_only)


RS = CameraSettings(exposure_s=650e-6, gain_db=0.0, pixel_format="BayerRG12", roi=(5472, 3648, 0, 0),
                    trigger_source="Line1", shutter_mode="Rolling")


def test_rs_gets_a_rolling_shutter_and_every_other_trigger_off():
    fm = ace_usb()
    fm.per["TriggerMode"]["FrameBurstStart"] = "On"  # left on by a previous program
    out = apply_settings(fm, RS, "RS camera 1")
    assert fm.values["ShutterMode"] == "Rolling" and out.features["ShutterMode"] == "Rolling"
    assert fm.per["TriggerMode"] == {"FrameBurstStart": "Off", "FrameStart": "On"}
    assert out.features["TriggerMode[FrameBurstStart]"] == "Off" and out.features["TriggerMode"] == "On"
    assert fm.values["TriggerSelector"] == "FrameStart" and out.warnings == []


def test_shutter_mode_where_it_cannot_be_set_is_recorded_with_a_warning():
    fm = ace_usb(read_only=("ShutterMode",))
    out = apply_settings(fm, RS, "RS camera 1")
    assert out.features["ShutterMode"] == "Global"
    assert out.warnings == ["RS camera 1: ShutterMode is 'Global' and cannot be set to 'Rolling'"]
    fm = ace_usb()
    fm.enums["ShutterMode"] = ["Global"]
    out = apply_settings(fm, RS, "RS camera 1")
    assert "ShutterMode offers Global, not Rolling; left as is" in out.warnings[0]


def test_a_rolling_only_sensor_without_shutter_mode_needs_nothing():
    fm = ace_usb(ShutterMode=None)
    out = apply_settings(fm, RS, "RS camera 1")
    assert "ShutterMode" not in out.features and out.warnings == []


def test_gs_shutter_is_left_alone():
    fm = ace_usb()
    apply_settings(fm, CameraSettings(exposure_s=650e-6, trigger_source="Line1"), "GS camera 2")
    assert fm.values["ShutterMode"] == "Global" and ("ShutterMode", "Rolling") not in fm.writes


def test_ace_gige_names_exposure_time_abs_and_gain_raw():
    fm = ace_usb(ExposureTime=None, Gain=None, ExposureTimeAbs=1000.0, GainRaw=300, ShutterMode=None)
    out = apply_settings(fm, CameraSettings(exposure_s=650e-6, gain_db=0.0), "GS camera 2")
    assert out.features["ExposureTimeAbs"] == 650.0 and out.features["exposure_s"] == pytest.approx(650e-6)
    assert fm.values["GainRaw"] == 0  # its minimum: the only unambiguous "no gain"
    with pytest.raises(HardwareError, match="only GainRaw"):
        apply_settings(fm, CameraSettings(gain_db=6.0), "GS camera 2")
