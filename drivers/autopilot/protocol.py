"""MAVLink facts the autopilot link uses (common.xml, ardupilotmega.xml): enum values, the setpoint
type mask, ArduCopter's and PX4's flight modes by number and by name, and STATUSTEXT chunking.

Values and functions of values only; the link's parts import them from here.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

MAV_TYPE_GCS = mavlink2.MAV_TYPE_GCS  # 6
MAV_TYPE_ONBOARD_CONTROLLER = mavlink2.MAV_TYPE_ONBOARD_CONTROLLER  # 18
MAV_AUTOPILOT_ARDUPILOTMEGA = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA  # 3
MAV_AUTOPILOT_PX4 = mavlink2.MAV_AUTOPILOT_PX4  # 12
MAV_AUTOPILOT_INVALID = mavlink2.MAV_AUTOPILOT_INVALID  # 8
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_STATE_ACTIVE = mavlink2.MAV_STATE_ACTIVE
MAV_RESULT_IN_PROGRESS = 5

# POSITION_TARGET_TYPEMASK (common.xml): a set bit means "ignore this field".
TYPEMASK_X, TYPEMASK_Y, TYPEMASK_Z = 1, 2, 4
TYPEMASK_VX, TYPEMASK_VY, TYPEMASK_VZ = 8, 16, 32
TYPEMASK_AX, TYPEMASK_AY, TYPEMASK_AZ = 64, 128, 256
TYPEMASK_YAW, TYPEMASK_YAW_RATE = 1024, 2048
TYPEMASK_POSITION = TYPEMASK_X | TYPEMASK_Y | TYPEMASK_Z
TYPEMASK_ACCEL = TYPEMASK_AX | TYPEMASK_AY | TYPEMASK_AZ
TYPEMASK_VELOCITY_ONLY = TYPEMASK_POSITION | TYPEMASK_ACCEL | TYPEMASK_YAW | TYPEMASK_YAW_RATE  # 3527

PX4_MAIN_MODES = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED", 8: "RATTITUDE"}
PX4_AUTO_SUB_MODES = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF"}
PX4_MAIN_OFFBOARD = 6
PX4_SET_MODE = {  # name -> (main mode, sub mode)
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "TAKEOFF": (4, 2), "LOITER": (4, 3), "HOLD": (4, 3),
    "MISSION": (4, 4), "RTL": (4, 5), "LAND": (4, 6), "ACRO": (5, 0), "OFFBOARD": (6, 0), "STABILIZED": (7, 0),
}  # fmt: skip
ARDUCOPTER_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL", 7: "CIRCLE", 9: "LAND",
    11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD", 17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB",
    20: "GUIDED_NOGPS", 21: "SMART_RTL", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID", 26: "AUTOROTATE",
    27: "AUTO_RTL", 28: "TURTLE",
}  # fmt: skip
MULTIROTOR_TYPES = {2, 3, 4, 13, 14, 15, 29, 35}  # quad, coax, heli, hexa, octo, tri, dodeca, deca

SEVERITIES = {name: value for value, name in ((v, e.name.removeprefix("MAV_SEVERITY_")) for v, e in mavlink2.enums["MAV_SEVERITY"].items()) if name != "ENUM_END"}
STATUSTEXT_CHUNK = 50  # bytes per STATUSTEXT.text
STATUSTEXT_MAX_CHUNKS = 5


def result_name(value: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(int(value))
    return entry.name.removeprefix("MAV_RESULT_") if entry else f"RESULT_{value}"


def statustext_chunks(text: str) -> list[bytes]:
    """Split UTF-8 text into STATUSTEXT payloads (<= 50 bytes, on character boundaries, <= 5 chunks)."""
    data = text.encode("utf-8")
    limit = STATUSTEXT_CHUNK * STATUSTEXT_MAX_CHUNKS
    if len(data) > limit:
        cut = limit - 4  # 249 bytes with the ellipsis: the last chunk is not full, so no terminator chunk
        while cut > 0 and (data[cut] & 0xC0) == 0x80:
            cut -= 1
        data = data[:cut] + b"..."
    if len(data) <= STATUSTEXT_CHUNK:
        return [data]
    chunks = []
    while data:
        cut = min(STATUSTEXT_CHUNK, len(data))
        while cut < len(data) and cut > 0 and (data[cut] & 0xC0) == 0x80:  # do not split a character
            cut -= 1
        chunks.append(data[:cut])
        data = data[cut:]
    if len(chunks[-1]) == STATUSTEXT_CHUNK:
        chunks.append(b"")  # a NUL-terminated (empty) chunk marks the end
    return chunks


def mav_type_name(mav_type: int) -> str:
    entry = mavlink2.enums["MAV_TYPE"].get(int(mav_type))
    return entry.name.removeprefix("MAV_TYPE_") if entry is not None else f"TYPE_{mav_type}"


def ardupilot_mode_table(mav_type: int) -> dict[int, str]:
    if mav_type in MULTIROTOR_TYPES:
        return ARDUCOPTER_MODES
    from pymavlink import mavutil  # other vehicle types: pymavlink's tables (imported only when needed)

    return mavutil.mode_mapping_bynumber(mav_type) or {}


def ardupilot_mode_name(mav_type: int, custom_mode: int) -> str:
    return ardupilot_mode_table(mav_type).get(custom_mode, f"MODE_{custom_mode}")


def px4_mode_name(custom_mode: int) -> str:
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    name = PX4_MAIN_MODES.get(main, f"MAIN_{main}")
    if main == 4:
        return f"AUTO.{PX4_AUTO_SUB_MODES.get(sub, sub)}"
    return name
