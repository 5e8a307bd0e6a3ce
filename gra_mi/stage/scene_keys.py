"""Every Mitsuba object id and ``mi.traverse`` key gra-mi relies on, spelled once.

Scene files (scenes/*.xml) and the code that edits loaded scenes both use these names; tests check that a
loaded scene exposes each of them.
"""

from __future__ import annotations

SUBJECT_ID = "subject"
SUBJECT_POSITIONS = f"{SUBJECT_ID}.vertex_positions"
SUBJECT_NORMALS = f"{SUBJECT_ID}.vertex_normals"
LED_PREFIX = "led_"
NORMALMAP_DATA_SUFFIX = "normalmap.data"
"""The traverse key of a ``normalmap`` BSDF's texture ends so (the capture's ground truth poses its wrinkles there)."""

# Scene-file parameters ($name in the XML, passed to mi.load_file as keyword arguments).
PARAM_SUBJECT = "subject"  # folder of the tracked mesh sequence, relative to the scene file
PARAM_FRAME = "frame"  # zero-padded frame number of the PLY to load first
PARAM_SPP = "spp"
PARAM_CALIBRATION = "calibration"  # the lightstage calibration JSON the LEDs and cameras came from


def led_id(index: int) -> str:
    return f"{LED_PREFIX}{index:03d}"


def led_intensity(index: int) -> str:
    return f"{led_id(index)}.intensity.value"


def led_sampling_weight(index: int) -> str:
    """How often the path tracer picks this LED for next-event estimation (relative to the others)."""
    return f"{led_id(index)}.sampling_weight"


def led_position(index: int) -> str:
    return f"{led_id(index)}.position"


def frame_param(frame: int) -> str:
    return f"{frame:04d}"
