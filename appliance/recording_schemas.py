"""The topics of a session recording and the JSON Schemas that describe them to MCAP viewers.

Every structured topic is a JSON-encoded MCAP channel with a JSON Schema (schema encoding
``jsonschema``), so Foxglove and Lichtblick show the messages in their Raw Messages, Plot and State
Transitions panels without any plugin. The schemas name the keys the appliance writes and their
types, but allow further keys (``additionalProperties``): the records grow, and an older viewer
layout must keep working.

The X-ray images are published as ``foxglove.RawImage`` (JSON encoding: ``data`` is the pixel
buffer in base64, ``encoding`` ``mono16``, little-endian, ``step`` = 2 x width), one channel per
plane, so the Image panel displays them as recorded (16-bit, auto-scaled by the viewer). The
biplane frame number travels in the MCAP message's ``sequence`` field, which every reader exposes.
"""
from __future__ import annotations

import json
from typing import Any

#: Format of the recording itself (kept in the MCAP header's profile and the ``/session`` message).
PROFILE = "x-microrobot-session"
FORMAT_VERSION = 1

TOPIC_SESSION = "/session"
TOPIC_CONFIG = "/config"
TOPIC_CALIBRATION = "/calibration"
TOPIC_POSTURE = "/posture"
TOPIC_COMMAND = "/command"
TOPIC_CURRENTS = "/currents"
TOPIC_OTS = "/ots"
TOPIC_FAULT = "/fault"
TOPIC_STATUS = "/status"
TOPIC_TIMING = "/timing"
#: One image channel per X-ray plane (p, q).
TOPIC_IMAGE = {"p": "/xray/p/image", "q": "/xray/q/image"}

IMAGE_SCHEMA_NAME = "foxglove.RawImage"
IMAGE_ENCODING = "mono16"

_NUMBER_OR_NULL = {"type": ["number", "null"]}
_VECTOR3 = {"type": ["array", "null"], "items": _NUMBER_OR_NULL, "minItems": 3, "maxItems": 3}
_NUMBERS = {"type": "array", "items": _NUMBER_OR_NULL}


def _object(title: str, description: str, properties: dict[str, Any],
            required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": properties,
            "required": list(required), "additionalProperties": True}


#: topic -> (schema name, JSON Schema). Schema names are namespaced so they never collide with
#: the foxglove.* well-known schemas a viewer interprets specially.
SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    TOPIC_SESSION: ("microrobot.Session", _object(
        "Session", "What wrote this recording and how its times map to the loop's clock.",
        {"format_version": {"type": "integer"}, "created_utc": {"type": "string"},
         "frames_every": {"type": "integer"}, "appliance_version": {"type": "string"},
         "t0_s": _NUMBER_OR_NULL},
        ("format_version",))),
    TOPIC_CONFIG: ("microrobot.SessionConfig", _object(
        "Session config", "The session configuration the loop ran with (validated at load).", {})),
    TOPIC_CALIBRATION: ("microrobot.Calibration", _object(
        "Biplane calibration", "The calibration the appliance used (architecture.md contract, mm).",
        {"views": {"type": "object"}}, ("views",))),
    TOPIC_POSTURE: ("microrobot.Posture", _object(
        "Posture record", "The recognised posture of one biplane pair (architecture.md contract).",
        {"frame": {"type": "integer"}, "t": _NUMBER_OR_NULL, "ok": {"type": "boolean"},
         "ambiguous": {"type": "boolean"}, "centroid_mm": _VECTOR3, "direction": _VECTOR3,
         "tips_mm": {"type": ["array", "null"], "items": _VECTOR3},
         "head_identified": {"type": "boolean"}, "length_mm": _NUMBER_OR_NULL,
         "reprojection_px": _NUMBER_OR_NULL, "views": {"type": ["object", "null"]},
         "reason": {"type": ["string", "null"]}},
        ("frame", "ok"))),
    TOPIC_COMMAND: ("microrobot.Command", _object(
        "Controller command", "What the controller asked of the coils this step (T, N, A).",
        {"frame": {"type": ["integer", "null"]}, "mode": {"type": "string"},
         "field_T": _VECTOR3, "force_N": _VECTOR3, "commanded_a": _NUMBERS,
         "scale": _NUMBER_OR_NULL, "limited_by": {"type": ["string", "null"]}})),
    TOPIC_CURRENTS: ("microrobot.Currents", _object(
        "Coil currents", "Measured (amplifier read-back) and commanded current per channel, A.",
        {"measured_a": _NUMBERS, "commanded_a": _NUMBERS}, ("measured_a", "commanded_a"))),
    TOPIC_OTS: ("microrobot.OtsSample", _object(
        "Optical tracker sample", "Reference poses from the optical tracking system (its own frame, mm).",
        {})),
    TOPIC_FAULT: ("microrobot.Fault", _object(
        "Fault", "A fault or safety event: which device or stage, and why.",
        {"device": {"type": ["string", "null"]}, "reason": {"type": ["string", "null"]}})),
    TOPIC_STATUS: ("microrobot.DeviceStatus", _object(
        "Device status", "A device's periodic status; 'device' names it.",
        {"device": {"type": "string"}}, ("device",))),
    TOPIC_TIMING: ("microrobot.FrameTiming", _object(
        "Frame timing", "Wall-clock duration of every loop stage for one frame, microseconds.",
        {"frame": {"type": ["integer", "null"]},
         "stages_us": {"type": "object", "additionalProperties": {"type": "number"}}},
        ("frame", "stages_us"))),
}

#: foxglove.RawImage as its JSON Schema (field list from Foxglove's published schema).
RAW_IMAGE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": IMAGE_SCHEMA_NAME, "description": "A raw image", "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time",
                      "properties": {"sec": {"type": "integer", "minimum": 0},
                                     "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
        "frame_id": {"type": "string"},
        "width": {"type": "integer", "minimum": 0},
        "height": {"type": "integer", "minimum": 0},
        "encoding": {"type": "string"},
        "step": {"type": "integer", "minimum": 0},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


def schema_bytes(schema: dict[str, Any]) -> bytes:
    """The schema record's data: compact UTF-8 JSON."""
    return json.dumps(schema, separators=(",", ":")).encode("utf-8")
