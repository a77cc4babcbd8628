#!/usr/bin/env python3
"""Signed MAVLink 2 frames from pymavlink, for core/src/links/signing.rs's tests.

Needs `pip install pymavlink` (2.4.50 wrote the frames in the tests); no network. Key 00 01 ... 1f,
link 3, first timestamp 0x123456789A (pymavlink adds one per signed frame), system 1,
component 191. Prints one hex frame per line: a HEARTBEAT and a SET_POSITION_TARGET_LOCAL_NED.
"""
import os

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402


class Sink:
    def __init__(self):
        self.buf = b""

    def write(self, b):
        self.buf += b


mav = mavlink2.MAVLink(Sink(), srcSystem=1, srcComponent=191)
mav.signing.secret_key = bytes(range(32))
mav.signing.link_id = 3
mav.signing.timestamp = 0x123456789A
mav.signing.sign_outgoing = True
heartbeat = mav.heartbeat_encode(
    mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE
)
print(heartbeat.pack(mav).hex())
setpoint = mav.set_position_target_local_ned_encode(
    1234, 1, 1, mavlink2.MAV_FRAME_LOCAL_NED, 0x09F8, 1.5, -2.25, -1.0, 0, 0, 0, 0, 0, 0, 0.5, 0
)
print(setpoint.pack(mav).hex())
