//! Transports of the depth link: the wire between the camera side (the simulator's encoder)
//! and the core side (the core's `DepthReceiver`), both of which run in this process.
//!
//! | `--link` | wire |
//! |---|---|
//! | `sim` (default) | an in-process byte pipe: bytes arrive exactly as sent |
//! | `tcp:HOST:PORT` | a TCP connection to `HOST:PORT`; the peer is the wire and must send the bytes back (an echo service, `ser2net` or `socat` on a UART with a loopback plug, a network emulator) |
//! | `tcp-listen:[HOST:]PORT` | the same, but this process listens (on 127.0.0.1 unless `HOST` is given) and the peer connects, within [`ACCEPT_TIMEOUT`] |
//! | `serial:PATH[:BAUD]` | a serial device or pty (the `serialport` crate, 8N1, no flow control), at `BAUD` or `--link-baud`; the far end must send the bytes back (a TX–RX loopback plug, or a program on the pty's other side) |
//!
//! Whatever the wire, the camera side paces its bytes at the link's baud rate in simulated time,
//! and the core side reads what has come back. A wire is a [`Wire`]: an in-process [`Pipe`] or
//! any `std::io::Read + Write` stream in a [`StreamWire`], so the run loop does not know which
//! one it has; wrappers that are wires themselves add to any of them, as smoltcp's
//! `phy::FaultInjector<D: Device>` does: baud pacing ([`crate::link::pacing::Paced`]) and
//! faults ([`crate::link::fault::Faulty`]), stacked from the options by
//! [`crate::link::depth_link`].

use std::collections::VecDeque;
use std::fmt;
use std::io::{self, Read, Write};
use std::net::{TcpListener, TcpStream, ToSocketAddrs};
use std::str::FromStr;
use std::time::{Duration, Instant};

/// How long `tcp-listen` waits for its peer to connect.
pub const ACCEPT_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a write may make no progress (the peer not reading) before the wire has failed.
pub const WRITE_STALL_TIMEOUT: Duration = Duration::from_secs(10);

/// A depth-link transport as named on the command line. See the [module documentation](self).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TransportSpec {
    /// The in-process byte pipe.
    Sim,
    /// A TCP connection to a peer that sends the bytes back.
    Tcp {
        /// Host name or address.
        host: String,
        /// Port.
        port: u16,
    },
    /// Listen for one TCP peer that sends the bytes back.
    TcpListen {
        /// Address to listen on.
        host: String,
        /// Port.
        port: u16,
    },
    /// A serial device or pty whose far end sends the bytes back.
    Serial {
        /// Device path.
        path: String,
        /// Baud rate; `None`: the link's baud rate.
        baud: Option<u32>,
    },
}

const SYNTAX: &str = "sim, tcp:HOST:PORT, tcp-listen:[HOST:]PORT or serial:PATH[:BAUD]";

fn parse_port(spec: &str, port: &str) -> Result<u16, String> {
    match port.parse::<u16>() {
        Ok(p) => Ok(p),
        Err(_) => Err(format!("`{spec}`: `{port}` is not a port number (0-65535)")),
    }
}

impl FromStr for TransportSpec {
    type Err = String;

    fn from_str(spec: &str) -> Result<Self, String> {
        let (kind, rest) = match spec.split_once(':') {
            Some((k, r)) => (k, Some(r)),
            None => (spec, None),
        };
        match (kind, rest) {
            ("sim", None) => Ok(Self::Sim),
            ("tcp", Some(rest)) => match rest.rsplit_once(':') {
                Some((host, port)) if !host.is_empty() => Ok(Self::Tcp {
                    host: host.trim_start_matches('[').trim_end_matches(']').to_string(),
                    port: parse_port(spec, port)?,
                }),
                _ => Err(format!("`{spec}`: expected tcp:HOST:PORT")),
            },
            ("tcp-listen", Some(rest)) => {
                let (host, port) = match rest.rsplit_once(':') {
                    Some((host, port)) if !host.is_empty() => {
                        (host.trim_start_matches('[').trim_end_matches(']'), port)
                    }
                    Some(_) => return Err(format!("`{spec}`: expected tcp-listen:[HOST:]PORT")),
                    None => ("127.0.0.1", rest),
                };
                Ok(Self::TcpListen {
                    host: host.to_string(),
                    port: parse_port(spec, port)?,
                })
            }
            ("serial", Some(rest)) => {
                let (path, baud) = match rest.rsplit_once(':') {
                    Some((path, baud)) if baud.chars().all(|c| c.is_ascii_digit()) => {
                        match baud.parse::<u32>() {
                            Ok(b) if b > 0 => (path, Some(b)),
                            _ => return Err(format!("`{spec}`: `{baud}` is not a baud rate")),
                        }
                    }
                    _ => (rest, None),
                };
                if path.is_empty() {
                    return Err(format!("`{spec}`: expected serial:PATH[:BAUD]"));
                }
                Ok(Self::Serial {
                    path: path.to_string(),
                    baud,
                })
            }
            ("sim" | "tcp" | "tcp-listen" | "serial", _) => {
                Err(format!("`{spec}`: malformed; expected one of {SYNTAX}"))
            }
            _ => Err(format!(
                "`{spec}`: unknown transport `{kind}` (expected {SYNTAX})"
            )),
        }
    }
}

impl fmt::Display for TransportSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Sim => write!(f, "sim"),
            Self::Tcp { host, port } => write!(f, "tcp:{host}:{port}"),
            Self::TcpListen { host, port } => write!(f, "tcp-listen:{host}:{port}"),
            Self::Serial { path, baud: None } => write!(f, "serial:{path}"),
            Self::Serial { path, baud: Some(b) } => write!(f, "serial:{path}:{b}"),
        }
    }
}

/// The wire of the depth link: the camera side sends bytes in, the core side receives them.
pub trait Wire {
    /// Camera side: puts `bytes` on the wire.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Core side: appends the bytes that have arrived to `into` without waiting; returns how
    /// many.
    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize>;
    /// True if bytes arrive the moment they are sent (in-process); false if they travel
    /// through something outside that takes real time.
    fn is_immediate(&self) -> bool;
    /// Ends a burst of [`Wire::send`]s: a wrapper that holds bytes back until then (a fault
    /// injector keeping a frame to swap with the next) lets them go on.
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
    /// Simulated time has reached `now_s` (a paced wire earns the right to send more).
    fn advance(&mut self, _now_s: f64) {}
    /// Lets on what the simulated time so far allows (a paced wire's queue drains at its baud
    /// rate); a plain wire has nothing held.
    fn release(&mut self) -> io::Result<()> {
        Ok(())
    }
    /// True while bytes wait in the wire to go on.
    fn pending(&self) -> bool {
        false
    }
}

impl<W: Wire + ?Sized> Wire for Box<W> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        (**self).send(bytes)
    }
    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize> {
        (**self).receive(into)
    }
    fn is_immediate(&self) -> bool {
        (**self).is_immediate()
    }
    fn flush(&mut self) -> io::Result<()> {
        (**self).flush()
    }
    fn advance(&mut self, now_s: f64) {
        (**self).advance(now_s)
    }
    fn release(&mut self) -> io::Result<()> {
        (**self).release()
    }
    fn pending(&self) -> bool {
        (**self).pending()
    }
}

/// The in-process wire: a byte queue.
#[derive(Debug, Default)]
pub struct Pipe {
    bytes: VecDeque<u8>,
}

impl Wire for Pipe {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.bytes.extend(bytes);
        Ok(())
    }

    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize> {
        let n = self.bytes.len();
        into.extend(self.bytes.drain(..));
        Ok(n)
    }

    fn is_immediate(&self) -> bool {
        true
    }
}

/// A wire over a duplex byte stream whose peer sends back what it is sent. The stream must not
/// block for long: a non-blocking socket, or a serial port with a short timeout
/// (`WouldBlock` and `TimedOut` both mean "nothing now").
#[derive(Debug)]
pub struct StreamWire<S> {
    stream: S,
    /// Bytes read while a write waited for the peer to drain its side.
    inbox: Vec<u8>,
}

fn nothing_now(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut | io::ErrorKind::Interrupted
    )
}

impl<S: Read + Write> StreamWire<S> {
    /// A wire over `stream`.
    pub fn new(stream: S) -> Self {
        Self {
            stream,
            inbox: Vec::new(),
        }
    }

    fn pump(&mut self) -> io::Result<usize> {
        let mut buf = [0u8; 4096];
        let mut total = 0;
        loop {
            match self.stream.read(&mut buf) {
                Ok(0) => {
                    return Err(io::Error::new(
                        io::ErrorKind::UnexpectedEof,
                        "the peer closed the connection",
                    ))
                }
                Ok(n) => {
                    self.inbox.extend_from_slice(&buf[..n]);
                    total += n;
                }
                Err(e) if nothing_now(&e) => return Ok(total),
                Err(e) => return Err(e),
            }
        }
    }
}

impl<S: Read + Write> Wire for StreamWire<S> {
    fn send(&mut self, mut bytes: &[u8]) -> io::Result<()> {
        let mut last_progress = Instant::now();
        while !bytes.is_empty() {
            match self.stream.write(bytes) {
                Ok(0) => return Err(io::Error::new(io::ErrorKind::WriteZero, "the wire took no bytes")),
                Ok(n) => {
                    bytes = &bytes[n..];
                    last_progress = Instant::now();
                }
                Err(e) if nothing_now(&e) => {
                    // The peer is not keeping up: take in what it sent back, so that it can.
                    if self.pump()? == 0 {
                        if last_progress.elapsed() > WRITE_STALL_TIMEOUT {
                            return Err(io::Error::new(
                                io::ErrorKind::TimedOut,
                                "the peer stopped taking bytes",
                            ));
                        }
                        std::thread::sleep(Duration::from_millis(1));
                    }
                }
                Err(e) => return Err(e),
            }
        }
        self.stream.flush()
    }

    fn receive(&mut self, into: &mut Vec<u8>) -> io::Result<usize> {
        self.pump()?;
        let n = self.inbox.len();
        into.append(&mut self.inbox);
        Ok(n)
    }

    fn is_immediate(&self) -> bool {
        false
    }
}

fn resolve(host: &str, port: u16) -> Result<std::net::SocketAddr, String> {
    (host, port)
        .to_socket_addrs()
        .map_err(|e| format!("{host}:{port}: {e}"))?
        .next()
        .ok_or_else(|| format!("{host}:{port}: no address"))
}

/// Opens the wire `spec` names; `baud` is the link's baud rate (for a serial device without
/// one of its own).
pub fn open(spec: &TransportSpec, baud: u32) -> Result<Box<dyn Wire>, String> {
    let err = |e: &dyn fmt::Display| format!("--link {spec}: {e}");
    match spec {
        TransportSpec::Sim => Ok(Box::new(Pipe::default())),
        TransportSpec::Tcp { host, port } => {
            let addr = resolve(host, *port).map_err(|e| err(&e))?;
            let stream = TcpStream::connect_timeout(&addr, Duration::from_secs(5)).map_err(|e| err(&e))?;
            tcp_wire(stream).map_err(|e| err(&e))
        }
        TransportSpec::TcpListen { host, port } => {
            let listener = TcpListener::bind((host.as_str(), *port)).map_err(|e| err(&e))?;
            let stream = accept_within(&listener, ACCEPT_TIMEOUT).map_err(|e| err(&e))?;
            tcp_wire(stream).map_err(|e| err(&e))
        }
        TransportSpec::Serial { path, baud: own } => {
            let port = serialport::new(path.as_str(), own.unwrap_or(baud))
                .timeout(Duration::from_millis(1))
                .open()
                .map_err(|e| err(&e))?;
            Ok(Box::new(StreamWire::new(port)))
        }
    }
}

fn tcp_wire(stream: TcpStream) -> io::Result<Box<dyn Wire>> {
    stream.set_nodelay(true)?;
    stream.set_nonblocking(true)?;
    Ok(Box::new(StreamWire::new(stream)))
}

/// Accepts one connection on `listener`, or fails after `timeout`.
pub fn accept_within(listener: &TcpListener, timeout: Duration) -> io::Result<TcpStream> {
    listener.set_nonblocking(true)?;
    let start = Instant::now();
    loop {
        match listener.accept() {
            Ok((stream, _)) => {
                stream.set_nonblocking(false)?;
                return Ok(stream);
            }
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                if start.elapsed() > timeout {
                    return Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("no peer connected within {} s", timeout.as_secs()),
                    ));
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => return Err(e),
        }
    }
}

/// The far end of a loopback wire: copies everything `stream` receives back into it until the
/// other side closes. What `harmonic-sim link-echo` runs, and the tests' peer.
pub fn echo<S: Read + Write>(mut stream: S) -> io::Result<u64> {
    let mut buf = [0u8; 4096];
    let mut total = 0u64;
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return Ok(total),
            Ok(n) => {
                stream.write_all(&buf[..n])?;
                total += n as u64;
            }
            Err(e) if nothing_now(&e) => {}
            Err(e) if e.kind() == io::ErrorKind::ConnectionReset => return Ok(total),
            Err(e) => return Err(e),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_and_print_back() {
        for (text, spec) in [
            ("sim", TransportSpec::Sim),
            (
                "tcp:127.0.0.1:5760",
                TransportSpec::Tcp {
                    host: "127.0.0.1".into(),
                    port: 5760,
                },
            ),
            (
                "tcp-listen:0.0.0.0:5761",
                TransportSpec::TcpListen {
                    host: "0.0.0.0".into(),
                    port: 5761,
                },
            ),
            (
                "serial:/dev/ttyUSB0:921600",
                TransportSpec::Serial {
                    path: "/dev/ttyUSB0".into(),
                    baud: Some(921600),
                },
            ),
        ] {
            let parsed: TransportSpec = text.parse().unwrap();
            assert_eq!(parsed, spec);
            assert_eq!(parsed.to_string(), text);
        }
        assert_eq!(
            "tcp-listen:5762".parse::<TransportSpec>().unwrap(),
            TransportSpec::TcpListen {
                host: "127.0.0.1".into(),
                port: 5762
            }
        );
        assert_eq!(
            "serial:/dev/pts/3".parse::<TransportSpec>().unwrap(),
            TransportSpec::Serial {
                path: "/dev/pts/3".into(),
                baud: None
            }
        );
    }

    #[test]
    fn malformed_specs_name_the_problem() {
        for (text, needle) in [
            ("udp:1.2.3.4:5", "unknown transport `udp`"),
            ("tcp:5760", "expected tcp:HOST:PORT"),
            ("tcp:host:http", "`http` is not a port number"),
            ("tcp-listen:99999", "`99999` is not a port number"),
            ("serial:", "expected serial:PATH[:BAUD]"),
            ("serial:/dev/ttyS0:0", "`0` is not a baud rate"),
            ("sim:3", "malformed"),
            ("tcp", "malformed"),
        ] {
            let e = text.parse::<TransportSpec>().unwrap_err();
            assert!(e.contains(needle) && e.contains(text), "{text}: {e}");
        }
    }

    #[test]
    fn pipe_delivers_in_order() {
        let mut pipe = Pipe::default();
        pipe.send(&[1, 2, 3]).unwrap();
        pipe.send(&[4]).unwrap();
        let mut got = Vec::new();
        assert_eq!(pipe.receive(&mut got).unwrap(), 4);
        assert_eq!(pipe.receive(&mut got).unwrap(), 0);
        assert_eq!(got, [1, 2, 3, 4]);
    }

    #[test]
    fn tcp_loopback_through_an_echo_peer() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let peer = std::thread::spawn(move || {
            let (stream, _) = listener.accept().unwrap();
            echo(stream).unwrap()
        });
        let spec: TransportSpec = format!("tcp:127.0.0.1:{port}").parse().unwrap();
        let mut wire = open(&spec, 921600).unwrap();
        assert!(!wire.is_immediate());
        // More than the socket buffers hold, so writes must wait for the echo to be read.
        let sent: Vec<u8> = (0..3_000_000u32).map(|i| (i * 7 + i / 251) as u8).collect();
        let mut got = Vec::new();
        for chunk in sent.chunks(65536) {
            wire.send(chunk).unwrap();
            wire.receive(&mut got).unwrap();
        }
        let start = Instant::now();
        while got.len() < sent.len() && start.elapsed() < Duration::from_secs(10) {
            wire.receive(&mut got).unwrap();
        }
        assert_eq!(got.len(), sent.len());
        assert!(got == sent);
        drop(wire);
        assert_eq!(peer.join().unwrap(), sent.len() as u64);
    }

    #[cfg(unix)]
    #[test]
    fn serial_pty_loopback() {
        use serialport::SerialPort;
        // A pty pair: the simulator opens the device by path, the far end echoes.
        let (master, slave) = serialport::TTYPort::pair().expect("pty pair");
        let path = slave.name().expect("pty name");
        // The far end stays open until the test is done: closing a pty master hangs up the
        // slave, and its unread input with it.
        let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let stop = done.clone();
        let echo_thread = std::thread::spawn(move || {
            let mut master = master;
            master.set_timeout(Duration::from_millis(20)).unwrap();
            let mut buf = [0u8; 1024];
            let mut total = 0usize;
            let start = Instant::now();
            while !stop.load(std::sync::atomic::Ordering::Relaxed)
                && start.elapsed() < Duration::from_secs(20)
            {
                match master.read(&mut buf) {
                    Ok(n) => {
                        master.write_all(&buf[..n]).unwrap();
                        total += n;
                    }
                    Err(e) if nothing_now(&e) => {}
                    Err(e) => panic!("{e}"),
                }
            }
            total
        });
        let spec: TransportSpec = format!("serial:{path}:921600").parse().unwrap();
        let mut wire = open(&spec, 115200).unwrap();
        // Every byte value, delimiters included: a pty in raw mode must not translate any.
        let sent: Vec<u8> = (0..50_000u32).map(|i| (i % 256) as u8).collect();
        let mut got = Vec::new();
        for chunk in sent.chunks(1000) {
            wire.send(chunk).unwrap();
            wire.receive(&mut got).unwrap();
        }
        let start = Instant::now();
        while got.len() < sent.len() && start.elapsed() < Duration::from_secs(10) {
            wire.receive(&mut got).unwrap();
        }
        done.store(true, std::sync::atomic::Ordering::Relaxed);
        assert!(got == sent, "{} of {} bytes came back", got.len(), sent.len());
        assert_eq!(echo_thread.join().unwrap(), sent.len());
        drop(slave);
    }

    #[test]
    fn opening_a_missing_device_or_closed_port_is_an_error() {
        let e = open(&"serial:/dev/no-such-tty".parse().unwrap(), 921600)
            .err()
            .unwrap();
        assert!(e.contains("/dev/no-such-tty"), "{e}");
        let port = {
            let l = TcpListener::bind("127.0.0.1:0").unwrap();
            l.local_addr().unwrap().port()
        };
        let e = open(&format!("tcp:127.0.0.1:{port}").parse().unwrap(), 921600)
            .err()
            .unwrap();
        assert!(e.contains(&format!("tcp:127.0.0.1:{port}")), "{e}");
    }
}
