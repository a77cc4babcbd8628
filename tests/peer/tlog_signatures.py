#!/usr/bin/env python3
"""Checks the MAVLink 2 signatures in a .tlog with pymavlink.

Reads every record of the log (u64 big-endian timestamp, then one MAVLink frame as sent), and
for the frames of one sender component (the companion computer's, 191, by default) counts
MAVLink 1 frames, MAVLink 2 frames without a signature, and signed frames whose signature
pymavlink's parser accepts or rejects with the given key. Prints the counts as JSON.

    python3 tests/peer/tlog_signatures.py out/run.tlog --key 5a5a...5a [--component 191]
"""

import argparse
import json
import sys

from pymavlink.dialects.v20 import common as mavlink2


def frames(data):
    """(timestamp, frame bytes) of each record of a .tlog."""
    at = 0
    while at + 8 < len(data):
        stamp = int.from_bytes(data[at:at + 8], "big")
        magic = data[at + 8]
        if magic == 0xFD:
            n = data[at + 9]
            signed = data[at + 10] & 0x01
            length = 12 + n + (13 if signed else 0)
        elif magic == 0xFE:
            length = 8 + data[at + 9]
        else:
            raise ValueError(f"record at byte {at}: no MAVLink frame (0x{magic:02x})")
        yield stamp, data[at + 8:at + 8 + length]
        at += 8 + length


def main(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("tlog")
    p.add_argument("--key", required=True, help="the 32-byte secret key, 64 hex digits")
    p.add_argument("--component", type=int, default=191, help="sender component to check")
    args = p.parse_args(argv)
    key = bytes.fromhex(args.key)
    if len(key) != 32:
        sys.exit("--key must be 32 bytes (64 hex digits)")
    data = open(args.tlog, "rb").read()
    counts = {"frames": 0, "mavlink1": 0, "unsigned": 0, "good_signatures": 0,
              "bad_signatures": 0, "other_components": 0}
    # One parser per sender, as a receiver keeps one signing state per link.
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=0)
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = False
    unsigned_seen = [0]

    def refuse_unsigned(_mav, _msgid):
        unsigned_seen[0] += 1
        return False

    mav.signing.allow_unsigned_callback = refuse_unsigned
    for _stamp, frame in frames(data):
        if frame[0] == 0xFD:
            component = frame[6]
        else:
            component = frame[4]
        if component != args.component:
            counts["other_components"] += 1
            continue
        counts["frames"] += 1
        if frame[0] == 0xFE:
            counts["mavlink1"] += 1
            continue
        if not frame[2] & 0x01:
            counts["unsigned"] += 1
            continue
        before = mav.signing.goodsig_count
        try:
            mav.parse_buffer(bytes(frame))
        except mavlink2.MAVError:
            pass
        if mav.signing.goodsig_count > before:
            counts["good_signatures"] += 1
        else:
            counts["bad_signatures"] += 1
    print(json.dumps(counts))


if __name__ == "__main__":
    main(sys.argv[1:])
