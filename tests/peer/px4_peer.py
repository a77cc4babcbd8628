#!/usr/bin/env python3
"""An independent MAVLink autopilot for testing `harmonic-sim explore --mavlink udpin:...`.

Written on pymavlink from the MAVLink specification alone: it shares no code and no
conventions with the project's flight-stack emulator (host-sim/src/vehicle/flight.rs) or bridge
(core/src/links/mavlink.rs).

What it does, like a PX4 multirotor already armed in offboard mode:

* HEARTBEAT at 1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, armed, custom mode
  enabled with PX4's main mode OFFBOARD (6 << 16).
* LOCAL_POSITION_NED and ATTITUDE at --rate Hz. time_boot_ms counts from this script's
  start and is the time of the state a message describes (the estimator's sample time).
  With --latency-ms the message leaves that long after its sample. Position is NED
  (x North, y East, z Down); yaw is NED heading (0 = North, clockwise positive,
  (-pi, pi]); roll and pitch are zero. Velocities are the true ones (--velocities
  truthful) or zero (--velocities zero, the default).
* Motion, stepped at 50 Hz of the wall clock: straight toward the latest
  SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED, position and yaw used) at up to
  --speed m/s, turning the shortest way toward its yaw at up to --yaw-rate-deg deg/s.
  With --turn-only it never moves, it only turns.

It sends to the explorer (the explorer listens with udpin) from its own port and reads
the explorer's answers there. It exits --idle-exit-s seconds after the explorer stops
talking (or after --max-s), and then prints a JSON summary on stdout; with --truth FILE it
also writes its true state at every 50 Hz step (t_ms north east down yaw).
"""

import argparse
import json
import math
import os
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

STEP_S = 0.02  # 50 Hz
PX4_MAIN_MODE_OFFBOARD = 6
# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK).
X_IGNORE, Y_IGNORE, Z_IGNORE = 1, 2, 4
YAW_IGNORE = 1024


def wrap(angle):
    """Angle wrapped to (-pi, pi]."""
    a = math.fmod(angle + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--connect", required=True, help="HOST:PORT the explorer listens on (its udpin)")
    p.add_argument("--start", default="1.2,2.0,-1.2", help="start position N,E,D in metres")
    p.add_argument("--start-yaw-deg", type=float, default=90.0, help="start heading, NED degrees")
    p.add_argument("--rate", type=float, default=20.0, help="LOCAL_POSITION_NED + ATTITUDE rate, Hz")
    p.add_argument("--latency-ms", type=float, default=0.0, help="age of the state a pose message carries when it leaves")
    p.add_argument("--velocities", choices=["zero", "truthful"], default="zero")
    p.add_argument("--speed", type=float, default=1.0, help="maximum speed, m/s")
    p.add_argument("--yaw-rate-deg", type=float, default=90.0, help="maximum yaw rate, deg/s")
    p.add_argument("--turn-only", action="store_true", help="never move, only turn")
    p.add_argument("--idle-exit-s", type=float, default=5.0)
    p.add_argument("--max-s", type=float, default=3600.0)
    p.add_argument("--truth", help="write the true state at every step to this file")
    p.add_argument("--key", help="MAVLink 2 signing: the 32-byte secret key as 64 hex digits; sign "
                   "everything sent and drop (count) every unsigned frame received")
    p.add_argument("--inject-unsigned", type=int, default=0, metavar="N",
                   help="with --key: also send N unsigned COMMAND_LONG (land) and N unsigned SET_MODE "
                   "frames, one pair per second from 1 s, as an intruder on the network would")
    return p.parse_args(argv)


class Vehicle:
    """The true state of the simulated multirotor, NED."""

    def __init__(self, ned, yaw):
        self.n, self.e, self.d = ned
        self.yaw = wrap(yaw)
        self.vel = (0.0, 0.0, 0.0)
        self.yaw_speed = 0.0

    def step(self, target, target_yaw, speed, yaw_rate, dt, turn_only):
        if target is not None and not turn_only:
            dn, de, dd = target[0] - self.n, target[1] - self.e, target[2] - self.d
            dist = math.sqrt(dn * dn + de * de + dd * dd)
            s = min(dist, speed * dt)
            if dist > 1e-9 and s > 0.0:
                k = s / dist
                self.n += dn * k
                self.e += de * k
                self.d += dd * k
                self.vel = (dn * k / dt, de * k / dt, dd * k / dt)
            else:
                self.vel = (0.0, 0.0, 0.0)
        else:
            self.vel = (0.0, 0.0, 0.0)
        if target_yaw is not None:
            err = wrap(target_yaw - self.yaw)
            limit = yaw_rate * dt
            turn = err if abs(err) <= limit else math.copysign(limit, err)
            self.yaw = wrap(self.yaw + turn)
            self.yaw_speed = turn / dt
        else:
            self.yaw_speed = 0.0

    def snapshot(self):
        return (self.n, self.e, self.d, self.yaw, self.vel, self.yaw_speed)


def main(argv):
    args = parse_args(argv)
    ned = [float(v) for v in args.start.split(",")]
    if len(ned) != 3:
        sys.exit("--start wants N,E,D")
    vehicle = Vehicle(ned, math.radians(args.start_yaw_deg))
    master = mavutil.mavlink_connection(
        "udpout:" + args.connect, source_system=1, source_component=1, dialect="common"
    )
    mav = master.mav
    unsigned_refused = [0]
    if args.key:
        def refuse_unsigned(_mav, _msgid):
            unsigned_refused[0] += 1
            return False

        master.setup_signing(bytes.fromhex(args.key), sign_outgoing=True,
                             allow_unsigned_callback=refuse_unsigned, link_id=0)
    speed, yaw_rate = args.speed, math.radians(args.yaw_rate_deg)
    period_s = 1.0 / args.rate
    latency_s = args.latency_ms * 1e-3

    t0 = time.monotonic()
    sim_t = 0.0  # time of the vehicle's state, s since start (50 Hz steps)
    history = [(0.0, vehicle.snapshot())]  # (t, state) of recent steps, for latency
    next_pose_t = latency_s  # the first message leaves once its sample is old enough
    next_sample_t = 0.0
    next_heartbeat_t = 0.0
    next_injection_t = 1.0
    injected = 0
    target, target_yaw = None, None
    last_heard = None
    counts = {"setpoints": 0, "setpoints_ignored": 0, "heartbeats_in": 0, "poses_sent": 0, "status_texts": []}
    truth = open(args.truth, "w") if args.truth else None

    def time_boot_ms(t):
        return int(round(t * 1000.0)) & 0xFFFFFFFF

    while True:
        now = time.monotonic() - t0
        # Take in everything the explorer sent.
        while True:
            msg = master.recv_match(blocking=False)
            if msg is None:
                break
            last_heard = now
            kind = msg.get_type()
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                uses_position = not (msg.type_mask & (X_IGNORE | Y_IGNORE | Z_IGNORE))
                uses_yaw = not (msg.type_mask & YAW_IGNORE)
                if msg.coordinate_frame == mavutil.mavlink.MAV_FRAME_LOCAL_NED and uses_position and uses_yaw:
                    target, target_yaw = (msg.x, msg.y, msg.z), msg.yaw
                    counts["setpoints"] += 1
                else:
                    counts["setpoints_ignored"] += 1
            elif kind == "HEARTBEAT":
                counts["heartbeats_in"] += 1
            elif kind == "STATUSTEXT":
                counts["status_texts"].append(msg.text)
        if last_heard is not None and now - last_heard > args.idle_exit_s:
            break
        if now > args.max_s:
            break

        # Fly: fixed 50 Hz steps, catching up with the wall clock.
        while sim_t + STEP_S <= now:
            vehicle.step(target, target_yaw, speed, yaw_rate, STEP_S, args.turn_only)
            sim_t += STEP_S
            history.append((sim_t, vehicle.snapshot()))
            if truth:
                n, e, d, yaw, _, _ = vehicle.snapshot()
                truth.write(f"{time_boot_ms(sim_t)} {n:.5f} {e:.5f} {d:.5f} {yaw:.6f}\n")
        # Keep a second of history.
        while len(history) > 2 and history[1][0] < sim_t - 1.0 - latency_s:
            history.pop(0)

        if args.key and injected < args.inject_unsigned and now >= next_injection_t and last_heard is not None:
            next_injection_t += 1.0
            mav.signing.sign_outgoing = False
            mav.command_long_send(1, 191, mavutil.mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
            mav.set_mode_send(1, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0)
            mav.signing.sign_outgoing = True
            injected += 1
        if now >= next_heartbeat_t:
            next_heartbeat_t += 1.0
            mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_QUADROTOR,
                mavutil.mavlink.MAV_AUTOPILOT_PX4,
                mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                PX4_MAIN_MODE_OFFBOARD << 16,
                mavutil.mavlink.MAV_STATE_ACTIVE,
            )
        # Pose messages: each carries the newest state at least `latency` old, stamped with
        # that state's own time.
        if now >= next_pose_t:
            next_pose_t += period_s
            if next_pose_t < now:
                next_pose_t = now + period_s
            sample_t = now - latency_s
            sample = None
            for t, state in history:
                if t <= sample_t + 1e-9:
                    sample = (t, state)
            if sample is not None and sample[0] >= next_sample_t - 1e-9:
                t, (n, e, d, yaw, vel, yaw_speed) = sample
                truthful = args.velocities == "truthful"
                vn, ve, vd = vel if truthful else (0.0, 0.0, 0.0)
                yaw_speed = yaw_speed if truthful else 0.0
                ms = time_boot_ms(t)
                mav.local_position_ned_send(ms, n, e, d, vn, ve, vd)
                mav.attitude_send(ms, 0.0, 0.0, yaw, 0.0, 0.0, yaw_speed)
                counts["poses_sent"] += 1
                next_sample_t = t + 1e-6

        wake = min(next_pose_t, next_heartbeat_t, sim_t + STEP_S)
        time.sleep(max(0.0, min(0.005, wake - (time.monotonic() - t0))))

    if truth:
        truth.close()
    n, e, d, yaw, _, _ = vehicle.snapshot()
    counts["final"] = {"north": n, "east": e, "down": d, "yaw_deg": math.degrees(yaw)}
    counts["unsigned_refused"] = unsigned_refused[0]
    counts["unsigned_injected"] = 2 * injected
    counts["bad_signatures"] = getattr(mav.signing, "badsig_count", 0)
    counts["good_signatures"] = getattr(mav.signing, "goodsig_count", 0)
    print(json.dumps(counts))


if __name__ == "__main__":
    main(sys.argv[1:])
