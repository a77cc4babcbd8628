//! End to end over real transports: the depth link through a TCP connection and a pty, MAVLink
//! to a fake autopilot over UDP sockets, and a recorded .tlog read back.
//!
//! Each run is short (a few steps): what is tested is that the bytes make the round trip, not
//! the exploration (tests/explore.rs has that).

use std::net::{TcpListener, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use harmonic_core::mavlink::{encode_v2, MavHeader, MavlinkDecoder, AUTOPILOT_COMPONENT_ID, MAX_FRAME_LEN};
use harmonic_sim::link::depth_link::LinkConfig;
use harmonic_sim::link::transport::{self, TransportSpec};
use harmonic_sim::run::sim::{self, Report, SimConfig};
use harmonic_sim::vehicle::autopilot::{MavlinkConfig, MavlinkSpec};
use harmonic_sim::vehicle::flight::{FlightCounters, FlightEmulator};
use harmonic_sim::vehicle::tlog;
use harmonic_sim::world::scenario::Scenario;
use nalgebra::Point3;

fn apartment() -> Scenario {
    Scenario::builtin("apartment").unwrap()
}

fn short_run(transport: TransportSpec, steps: u32) -> Report {
    let cfg = SimConfig {
        max_scans: steps,
        link: LinkConfig {
            transport,
            ..LinkConfig::default()
        },
        ..SimConfig::default()
    };
    sim::run(&apartment(), &cfg, |_| {}).expect("run")
}

/// The same steps, the same bytes: a transport must be transparent.
fn assert_same_run(over: &Report, reference: &Report) {
    assert_eq!(over.scans, reference.scans);
    assert_eq!(over.link.depth_frames_integrated, over.link.depth_frames_sent);
    assert_eq!(over.link.bytes_received, reference.link.bytes_sent);
    assert_eq!(over.link.receiver, reference.link.receiver);
    for (a, b) in over.steps.iter().zip(&reference.steps) {
        assert_eq!((a.position, &a.outcome), (b.position, &b.outcome));
    }
    assert!((over.path_length_m - reference.path_length_m).abs() < 1e-9);
}

#[test]
fn depth_link_over_tcp_loopback() {
    // The peer is the wire: it sends back what it gets, as a UART loopback plug would.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let peer = std::thread::spawn(move || {
        let stream = transport::accept_within(&listener, Duration::from_secs(30)).unwrap();
        transport::echo(stream).unwrap()
    });
    let over_tcp = short_run(format!("tcp:127.0.0.1:{port}").parse().unwrap(), 12);
    let echoed = peer.join().unwrap();
    assert_eq!(over_tcp.link.transport, format!("tcp:127.0.0.1:{port}"));
    assert_eq!(echoed, over_tcp.link.bytes_sent);
    assert_same_run(&over_tcp, &short_run(TransportSpec::Sim, 12));
}

#[test]
fn depth_link_over_tcp_listen() {
    // This time the simulator listens and the peer connects.
    let port = {
        let probe = TcpListener::bind("127.0.0.1:0").unwrap();
        probe.local_addr().unwrap().port()
    };
    let peer = std::thread::spawn(move || {
        let start = Instant::now();
        loop {
            match std::net::TcpStream::connect(("127.0.0.1", port)) {
                Ok(stream) => return transport::echo(stream).unwrap(),
                Err(_) if start.elapsed() < Duration::from_secs(20) => {
                    std::thread::sleep(Duration::from_millis(10))
                }
                Err(e) => panic!("{e}"),
            }
        }
    });
    let r = short_run(format!("tcp-listen:127.0.0.1:{port}").parse().unwrap(), 4);
    assert_eq!(peer.join().unwrap(), r.link.bytes_sent);
    assert_same_run(&r, &short_run(TransportSpec::Sim, 4));
}

#[cfg(unix)]
#[test]
fn depth_link_over_a_pty() {
    use serialport::SerialPort;
    use std::io::{Read, Write};
    // A pty pair stands in for a serial cable: the simulator opens the slave by its path, a
    // thread on the master sends everything back.
    let (mut master, slave) = serialport::TTYPort::pair().expect("pty pair");
    let path = slave.name().expect("pty path");
    let done = Arc::new(AtomicBool::new(false));
    let stop = done.clone();
    let echo = std::thread::spawn(move || {
        master.set_timeout(Duration::from_millis(5)).unwrap();
        let mut buf = [0u8; 4096];
        let mut total = 0u64;
        while !stop.load(Ordering::Relaxed) {
            match master.read(&mut buf) {
                Ok(n) => {
                    master.write_all(&buf[..n]).unwrap();
                    total += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => panic!("{e}"),
            }
        }
        total
    });
    let r = short_run(format!("serial:{path}").parse().unwrap(), 4);
    done.store(true, Ordering::Relaxed);
    assert_eq!(echo.join().unwrap(), r.link.bytes_sent);
    assert_same_run(&r, &short_run(TransportSpec::Sim, 4));
    drop(slave);
}

/// A fake autopilot on a UDP socket: the flight-stack emulator, a vehicle that flies to its
/// setpoint at `speed` in real time, LOCAL_POSITION_NED + ATTITUDE back to whoever spoke last
/// (or to `send_to` from the start). Runs until `stop`; returns the emulator's counters and
/// the vehicle's last position.
fn fake_autopilot(
    socket: UdpSocket,
    send_to: Option<std::net::SocketAddr>,
    start: Point3<f32>,
    start_yaw: f32,
    speed: f32,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<(FlightCounters, Point3<f32>)> {
    std::thread::spawn(move || {
        socket.set_read_timeout(Some(Duration::from_millis(5))).unwrap();
        let mut emulator = FlightEmulator::new();
        let (mut position, mut yaw) = (start, start_yaw);
        let mut peer = send_to;
        let clock = Instant::now();
        let mut last = clock.elapsed();
        let mut buf = [0u8; 2048];
        while !stop.load(Ordering::Relaxed) {
            let now_ms = clock.elapsed().as_millis() as u64;
            if let Ok((n, from)) = socket.recv_from(&mut buf) {
                peer = Some(from);
                emulator.receive(now_ms, &buf[..n]);
            }
            let dt = (clock.elapsed() - last).as_secs_f32();
            last = clock.elapsed();
            if let Some(sp) = emulator.setpoint() {
                let d = sp.position - position;
                let step = (speed * dt).min(d.norm());
                if step > 1e-6 {
                    position += d * (step / d.norm());
                }
                yaw = sp.yaw;
            }
            let mut out = Vec::new();
            emulator.poll(now_ms, &position, yaw, &mut out);
            if let (Some(to), false) = (peer, out.is_empty()) {
                // One datagram per message, as PX4 sends them.
                let mut decoder = MavlinkDecoder::new();
                decoder.push_frames(&out, |frame, _| {
                    let _ = socket.send_to(frame, to);
                });
            }
        }
        // What the simulator sent before it stopped may still wait in the socket (this loop
        // reads one datagram a turn): read it, so every setpoint sent is counted.
        while let Ok((n, _)) = socket.recv_from(&mut buf) {
            emulator.receive(clock.elapsed().as_millis() as u64, &buf[..n]);
        }
        (*emulator.counters(), position)
    })
}

fn remote_run(spec: MavlinkSpec, steps: u32, tlog: Option<std::path::PathBuf>) -> Report {
    let cfg = SimConfig {
        max_scans: steps,
        // No look-around turns at the start: these runs are short and must fly.
        look_around: 1,
        mavlink: Some(MavlinkConfig {
            spec,
            tlog,
            ..MavlinkConfig::default()
        }),
        ..SimConfig::default()
    };
    sim::run(&apartment(), &cfg, |_| {}).expect("run against the fake autopilot")
}

#[test]
fn mavlink_udpout_to_a_fake_autopilot() {
    let scenario = apartment();
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let addr = socket.local_addr().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let peer = fake_autopilot(
        socket,
        None,
        scenario.start_position,
        scenario.start_yaw,
        2.0,
        stop.clone(),
    );
    // The first plans look around the start corner, then the vehicle moves.
    let r = remote_run(MavlinkSpec::UdpOut(addr), 6, None);
    stop.store(true, Ordering::Relaxed);
    let (autopilot, last_position) = peer.join().unwrap();

    let mav = r.mavlink.as_ref().unwrap();
    assert_eq!(mav.endpoint, format!("udpout:{addr}"));
    assert!(
        mav.emulator.is_none(),
        "no in-process emulator against a remote autopilot"
    );
    // The setpoints arrived over UDP, and were flown.
    assert!(autopilot.setpoints_received > 10, "{autopilot:?}");
    assert_eq!(autopilot.setpoints_rejected, 0);
    assert_eq!(autopilot.setpoints_received, mav.traffic.setpoints_sent);
    // Wall-clock time: a plan computed between two setpoints delays one, and loaded test
    // machines are slow; the 10 Hz stream must still never stop for a second.
    assert!(autopilot.max_setpoint_gap_ms < 1000, "{autopilot:?}");
    // The pose came back over UDP; the explorer planned from it and the vehicle moved.
    assert!(mav.bridge.local_positions_received > 20 && mav.bridge.attitudes_received > 20);
    assert_eq!(
        mav.traffic.received_by_type.get("LOCAL_POSITION_NED"),
        Some(&mav.bridge.local_positions_received)
    );
    assert_eq!(r.scans, 6);
    // The planner looks at near frontiers before it flies (the view rule): in six scans the
    // vehicle turns a lot and moves a little, but it moves.
    assert!(
        r.path_length_m > 0.1,
        "the remote vehicle flew {} m",
        r.path_length_m
    );
    let first = Point3::from(r.steps[0].position);
    assert!((first - scenario.start_position).norm() < 0.05);
    // (It flew, above; it may end near where it started, after looking around the corner.)
    let last = Point3::from(r.steps.last().unwrap().position);
    // The vehicle ends where the autopilot has it (it held its last setpoint).
    assert!((last_position - last).norm() < 1.2, "{last_position} vs {last}");
    assert_eq!(
        mav.status_texts.first().map(String::as_str),
        Some("exploration started")
    );
}

#[test]
fn mavlink_udpin_answers_the_autopilot_and_records_a_tlog() {
    let scenario = apartment();
    // The simulator listens; the autopilot sends to it first (PX4 sends to 14540 on its own).
    let port = UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let listen: std::net::SocketAddr = ([127, 0, 0, 1], port).into();
    let socket = UdpSocket::bind("127.0.0.1:0").unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let peer = fake_autopilot(
        socket,
        Some(listen),
        scenario.start_position,
        scenario.start_yaw,
        2.0,
        stop.clone(),
    );
    let path = std::env::temp_dir().join(format!("harmonic-udpin-{}.tlog", std::process::id()));
    let r = remote_run(MavlinkSpec::UdpIn(listen), 2, Some(path.clone()));
    stop.store(true, Ordering::Relaxed);
    let (autopilot, _) = peer.join().unwrap();
    let mav = r.mavlink.as_ref().unwrap();
    assert!(
        autopilot.setpoints_received > 5 && autopilot.heartbeats_received > 0,
        "{autopilot:?}"
    );
    assert!(mav.bridge.local_positions_received > 10);
    // Wall-clock timestamps in the log of a remote run.
    let records = tlog::read_records(&std::fs::read(&path).unwrap()).unwrap();
    let now_us = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_micros() as u64;
    let first = records.first().unwrap().timestamp_us;
    assert!(
        first <= now_us && now_us - first < 120_000_000,
        "{first} vs {now_us}"
    );
    let summary = tlog::summarize(&records, 191);
    assert_eq!(summary.sent, mav.traffic.sent_by_type);
    assert_eq!(summary.received, mav.traffic.received_by_type);
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn tlog_holds_every_message_sent_and_received() {
    let path = std::env::temp_dir().join(format!("harmonic-tlog-{}/run.tlog", std::process::id()));
    let cfg = SimConfig {
        max_scans: 8,
        mavlink: Some(MavlinkConfig {
            tlog: Some(path.clone()),
            odometry: true,
            ..MavlinkConfig::default()
        }),
        ..SimConfig::default()
    };
    let r = sim::run(&apartment(), &cfg, |_| {}).unwrap();
    let mav = r.mavlink.as_ref().unwrap();
    let records = tlog::read_records(&std::fs::read(&path).unwrap()).unwrap();
    assert_eq!(records.len() as u64, mav.tlog.as_ref().unwrap().records);
    assert_eq!(
        records.len() as u32,
        mav.traffic.messages_sent + mav.traffic.messages_received
    );
    // Simulated time from the fixed epoch, in order.
    assert_eq!(records[0].timestamp_us, tlog::SIM_EPOCH_US);
    assert!(records.windows(2).all(|w| w[0].timestamp_us <= w[1].timestamp_us));
    let span = records.last().unwrap().timestamp_us - records[0].timestamp_us;
    assert!(
        (span as f64 * 1e-6 - r.flight_time_s).abs() < 0.11,
        "{span} µs vs {} s",
        r.flight_time_s
    );
    // Every record decodes, into exactly the messages counted each way.
    let summary = tlog::summarize(&records, 191);
    assert_eq!(summary.undecoded, 0);
    assert_eq!(summary.sent, mav.traffic.sent_by_type);
    assert_eq!(summary.received, mav.traffic.received_by_type);
    assert!(summary.received.get("ODOMETRY").is_some_and(|&n| n > 10));
    assert_eq!(mav.bridge.odometries_received, summary.received["ODOMETRY"]);
    // The setpoints in the log are the ones the emulator flew.
    let setpoints: Vec<_> = records
        .iter()
        .filter_map(|rec| match tlog::decode(rec) {
            Some((h, harmonic_core::mavlink::MavMessage::SET_POSITION_TARGET_LOCAL_NED(d))) => Some((h, d)),
            _ => None,
        })
        .collect();
    assert_eq!(setpoints.len() as u32, mav.emulator.unwrap().setpoints_received);
    assert!(setpoints.iter().all(|(h, d)| h.component_id == 191
        && d.target_component == AUTOPILOT_COMPONENT_ID
        && d.coordinate_frame == harmonic_core::mavlink::common::MavFrame::MAV_FRAME_LOCAL_NED));
    // Re-encoding a decoded record gives back its bytes: the log holds real MAVLink 2 frames.
    let (h, m) = tlog::decode(&records[0]).unwrap();
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = encode_v2(&MavHeader { ..h }, &m, &mut buf).unwrap();
    assert_eq!(&buf[..n], &records[0].frame[..]);
    std::fs::remove_dir_all(path.parent().unwrap()).unwrap();
}
