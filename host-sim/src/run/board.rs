//! Where the companion runs: the firmware on an emulated Cortex-M4F ([`Qemu`]), or the very same
//! [`Companion`](harmonic_core::companion::Companion) in this process ([`InProcess`]): with the
//! firmware's grid, storage and configuration, or with the run's (any scenario's grid, any
//! planner).
//!
//! Either way the simulator talks to it only through its two byte streams, the depth link
//! (UART0) and MAVLink (UART1), and a [`Board`] is all the processor-in-the-loop run
//! ([`crate::run::pil`]) needs: send bytes, read what came back, notice a board that stopped.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::io::{Read, Write};
use std::mem::MaybeUninit;
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use harmonic_core::companion::{Companion, CompanionConfig, GeometryWait, Waited};
use harmonic_core::explore::{Explorer, HarmonicField, TargetChoice};
use harmonic_core::map::MapGeometry;
use harmonic_core::signing::SecretKey;
use harmonic_fw::app as fw;

use crate::planners::HostClock;
use crate::run::sim::SimError;

/// One of a board's two byte streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Port {
    /// The depth link (UART0): images in; resend requests, map and plan reports out.
    Link,
    /// MAVLink (UART1): the autopilot's poses and TIMESYNC requests in; setpoints out.
    Mavlink,
}

/// A companion computer the simulator can talk to.
pub trait Board {
    /// Writes `bytes` to the companion's `port`.
    fn send(&mut self, port: Port, bytes: &[u8]) -> Result<(), SimError>;
    /// Reads what the companion wrote on `port` into `buf`, waiting a short while at most;
    /// `Ok(0)` if nothing came.
    fn receive(&mut self, port: Port, buf: &mut [u8]) -> Result<usize, SimError>;
    /// Fails if the companion has stopped.
    fn check_alive(&mut self) -> Result<(), SimError>;
    /// Where the companion runs, for reports: `qemu` or `in-process`.
    fn name(&self) -> &'static str;
}

fn io(what: &str) -> impl Fn(std::io::Error) -> SimError + '_ {
    move |e| SimError::Config(format!("{what}: {e}"))
}

/// QEMU running the firmware, with its two UARTs on local TCP sockets and the log it writes.
pub struct Qemu {
    child: Child,
    link: TcpStream,
    mav: TcpStream,
    command: String,
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Qemu {
    /// Starts `qemu` on the firmware `elf`, its defmt log (`firmware.defmt`) and QEMU's own
    /// (`qemu.log`) written into `out`, and connects to both UARTs.
    pub fn start(qemu: &str, elf: &Path, out: &Path) -> Result<Self, SimError> {
        let listen = || TcpListener::bind("127.0.0.1:0").map_err(io("bind a local port"));
        let (l0, l1) = (listen()?, listen()?);
        let port = |l: &TcpListener| l.local_addr().map(|a| a.port()).map_err(io("local port"));
        let (p0, p1) = (port(&l0)?, port(&l1)?);
        let defmt = std::fs::File::create(out.join("firmware.defmt")).map_err(io("firmware.defmt"))?;
        let qemu_log = std::fs::File::create(out.join("qemu.log")).map_err(io("qemu.log"))?;
        let args: Vec<String> = machine_args()
            .chain([
                "-serial".into(),
                format!("tcp:127.0.0.1:{p0}"),
                "-serial".into(),
                format!("tcp:127.0.0.1:{p1}"),
                "-kernel".into(),
                elf.display().to_string(),
            ])
            // Extra QEMU options for debugging, e.g. `-monitor unix:/tmp/m.sock,server=on,wait=off`.
            .chain(
                std::env::var("HARMONIC_QEMU_EXTRA")
                    .unwrap_or_default()
                    .split_whitespace()
                    .map(str::to_string),
            )
            .collect();
        let command = format!("{qemu} {}", args.join(" "));
        let mut child = Command::new(qemu)
            .args(&args)
            .stdin(Stdio::null())
            .stdout(defmt)
            .stderr(qemu_log)
            .spawn()
            .map_err(|e| {
                SimError::Config(format!(
                    "cannot start {qemu}: {e} (is qemu-system-arm installed?)"
                ))
            })?;
        let streams = accept(&l0, &mut child).and_then(|link| Ok((link, accept(&l1, &mut child)?)));
        let (link, mav) = match streams {
            Ok(s) => s,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(e);
            }
        };
        let board = Qemu {
            child,
            link,
            mav,
            command,
        };
        for s in [&board.link, &board.mav] {
            s.set_nodelay(true).map_err(io("TCP_NODELAY"))?;
            s.set_read_timeout(Some(Duration::from_millis(200)))
                .map_err(io("read timeout"))?;
        }
        Ok(board)
    }

    /// The QEMU command line.
    pub fn command(&self) -> &str {
        &self.command
    }

    fn stream(&mut self, port: Port) -> &mut TcpStream {
        match port {
            Port::Link => &mut self.link,
            Port::Mavlink => &mut self.mav,
        }
    }
}

impl Board for Qemu {
    fn send(&mut self, port: Port, bytes: &[u8]) -> Result<(), SimError> {
        let what = match port {
            Port::Link => "UART0 write",
            Port::Mavlink => "UART1 write",
        };
        self.stream(port).write_all(bytes).map_err(io(what))
    }

    fn receive(&mut self, port: Port, buf: &mut [u8]) -> Result<usize, SimError> {
        match self.stream(port).read(buf) {
            Ok(0) => Err(SimError::Config("the firmware closed its UART".into())),
            Ok(n) => Ok(n),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::Interrupted
                ) =>
            {
                Ok(0)
            }
            Err(e) => Err(io("UART read")(e)),
        }
    }

    fn check_alive(&mut self) -> Result<(), SimError> {
        match self.child.try_wait() {
            Ok(Some(status)) => Err(SimError::Config(format!(
                "the firmware stopped (QEMU exited: {status}); see its log"
            ))),
            _ => Ok(()),
        }
    }

    fn name(&self) -> &'static str {
        "qemu"
    }
}

fn accept(listener: &TcpListener, child: &mut Child) -> Result<TcpStream, SimError> {
    listener.set_nonblocking(true).map_err(io("listener"))?;
    let start = Instant::now();
    loop {
        match listener.accept() {
            Ok((s, _)) => {
                s.set_nonblocking(false).map_err(io("socket"))?;
                return Ok(s);
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if let Ok(Some(status)) = child.try_wait() {
                    return Err(SimError::Config(format!(
                        "QEMU exited before connecting: {status}"
                    )));
                }
                if start.elapsed() > Duration::from_secs(30) {
                    return Err(SimError::Config(
                        "QEMU did not connect its UARTs within 30 s".into(),
                    ));
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => return Err(io("accept")(e)),
        }
    }
}

/// QEMU's board (mps2-an386, Cortex-M4, no display, monitor, network or default devices),
/// semihosting on, and [`icount_args`]; the caller adds the serial ports and the image.
pub(crate) fn machine_args() -> impl Iterator<Item = String> {
    [
        "-machine",
        "mps2-an386",
        "-cpu",
        "cortex-m4",
        "-display",
        "none",
        "-monitor",
        "none",
        "-nodefaults",
        "-nic",
        "none",
        "-semihosting-config",
        "enable=on,target=native",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain(icount_args())
}

/// `-icount shift=0`: deterministic instruction counting (1 ns of board time per instruction),
/// unless `HARMONIC_QEMU_ICOUNT=0`.
fn icount_args() -> Vec<String> {
    if std::env::var("HARMONIC_QEMU_ICOUNT").is_ok_and(|v| v == "0") {
        Vec::new()
    } else {
        vec!["-icount".into(), "shift=0,align=off".into()]
    }
}

/// One direction-pair of an in-process UART: bytes the simulator sent, waiting for the
/// companion, and bytes the companion wrote, waiting for the simulator.
#[derive(Debug, Default)]
struct Pipe {
    to_companion: VecDeque<u8>,
    from_companion: VecDeque<u8>,
}

impl embedded_io::ErrorType for Pipe {
    type Error = Infallible;
}

impl embedded_io::Read for Pipe {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let n = buf.len().min(self.to_companion.len());
        for (slot, byte) in buf.iter_mut().zip(self.to_companion.drain(..n)) {
            *slot = byte;
        }
        Ok(n)
    }
}

impl embedded_io::ReadReady for Pipe {
    fn read_ready(&mut self) -> Result<bool, Infallible> {
        Ok(!self.to_companion.is_empty())
    }
}

impl embedded_io::Write for Pipe {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        self.from_companion.extend(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// The companion [`InProcess`] runs: the firmware's link decoder and signing streams.
pub type InProcessCompanion<'a, T> = Companion<'a, { fw::LINK_DECODER_BYTES }, { fw::SIGNING_STREAMS }, T>;

/// Builds the companion for the grid that came (carving the storage for it).
type Build<'a, T> = Box<dyn FnOnce(MapGeometry) -> Result<InProcessCompanion<'a, T>, SimError> + 'a>;

/// Where an [`InProcess`] board is in its mission.
enum State<'a, T: TargetChoice> {
    /// Waiting for the grid, as the firmware does at boot ([`GeometryWait`], [`fw::fits`]).
    Waiting { wait: GeometryWait, build: Build<'a, T> },
    /// Exploring (boxed: the companion is some 6 KiB, the wait a few hundred bytes).
    Running(Box<InProcessCompanion<'a, T>>),
    /// Building the companion failed (the error was returned).
    Failed,
}

/// A companion running in this process: the same code the firmware runs, built for the host,
/// with the firmware's capacity, storage ([`fw::build_explorer`]) and configuration
/// ([`fw::companion_config`]) ([`InProcess::start`]: it waits for the grid as the firmware
/// does), or around any explorer and configuration ([`InProcess::new`]); the firmware's link
/// decoder and signing streams either way. Its clock is the host's (nanoseconds), so the tick
/// counts in its reports are wall time, not instructions. Bytes sent are acted on before
/// [`Board::send`] returns, so a run is deterministic as under QEMU's lockstep.
pub struct InProcess<'a, T: TargetChoice = HarmonicField<'a>> {
    state: State<'a, T>,
    link: Pipe,
    mav: Pipe,
    clock: HostClock,
}

/// Ticks per second of [`InProcess`]'s clock.
pub const IN_PROCESS_TICK_HZ: u32 = 1_000_000_000;

impl<'a> InProcess<'a> {
    /// The firmware's companion over `storage` (the firmware's own buffers: put them on the
    /// heap, `Box::new(fw::Storage::new())`), its explorer built in `slot` for the grid that
    /// comes over the depth link, signing MAVLink with `key` if one is given (the firmware
    /// builds its key in; here it is the run's).
    pub fn start(
        storage: &'a mut fw::Storage,
        slot: &'a mut MaybeUninit<Explorer<'a>>,
        key: Option<SecretKey>,
    ) -> Self {
        let build = move |geometry| {
            let config_err = |e| SimError::Config(format!("the firmware's companion: {e:?}"));
            let (explorer, depth) = fw::build_explorer(storage, geometry, slot).map_err(config_err)?;
            let mut config = fw::companion_config(IN_PROCESS_TICK_HZ);
            config.signing_key = key;
            Companion::new(explorer, depth, config).map_err(config_err)
        };
        Self {
            state: State::Waiting {
                wait: GeometryWait::new(),
                build: Box::new(build),
            },
            link: Pipe::default(),
            mav: Pipe::default(),
            clock: HostClock::new(),
        }
    }
}

impl<'a, T: TargetChoice> InProcess<'a, T> {
    /// A companion around `explorer`, receiving depth images of up to `depth.len()` pixels,
    /// configured by `config` (its clock ticks at [`IN_PROCESS_TICK_HZ`]); its grid is the
    /// explorer's.
    pub fn new(
        explorer: &'a mut Explorer<'a, T>,
        depth: &'a mut [u16],
        config: CompanionConfig,
    ) -> Result<Self, SimError> {
        let companion = Companion::new(explorer, depth, config)
            .map_err(|e| SimError::Config(format!("the companion: {e:?}")))?;
        Ok(Self {
            state: State::Running(Box::new(companion)),
            link: Pipe::default(),
            mav: Pipe::default(),
            clock: HostClock::new(),
        })
    }

    /// The companion (its explorer, bridge and counters), once the mission's grid came.
    pub fn companion(&self) -> Option<&InProcessCompanion<'a, T>> {
        match &self.state {
            State::Running(c) => Some(c),
            _ => None,
        }
    }

    fn pipe(&mut self, port: Port) -> &mut Pipe {
        match port {
            Port::Link => &mut self.link,
            Port::Mavlink => &mut self.mav,
        }
    }

    /// Before the mission: reads the depth link for the grid (MAVLink waits in its pipe, as
    /// in a UART's); builds the companion once one fits.
    fn wait_for_grid(&mut self) -> Result<(), SimError> {
        let State::Waiting { wait, .. } = &mut self.state else {
            return Ok(());
        };
        loop {
            let waited = wait
                .poll(&mut self.link, fw::fits)
                .map_err(|e| SimError::Config(format!("the companion's {e:?} stream failed")))?;
            match waited {
                Waited::Taken(geometry) => {
                    let State::Waiting { build, .. } = std::mem::replace(&mut self.state, State::Failed)
                    else {
                        return Ok(());
                    };
                    self.state = State::Running(Box::new(build(geometry)?));
                    return Ok(());
                }
                Waited::Refused(..) => continue,
                Waited::Nothing => return Ok(()),
            }
        }
    }
}

impl<T: TargetChoice> Board for InProcess<'_, T> {
    fn send(&mut self, port: Port, bytes: &[u8]) -> Result<(), SimError> {
        self.pipe(port).to_companion.extend(bytes);
        self.wait_for_grid()?;
        while !(self.link.to_companion.is_empty() && self.mav.to_companion.is_empty()) {
            let Self {
                state,
                link,
                mav,
                clock,
            } = self;
            let State::Running(companion) = state else {
                // Still waiting for the grid: the rest stays queued.
                return Ok(());
            };
            companion
                .poll(link, mav, clock, |_| {})
                .map_err(|e| SimError::Config(format!("the companion's {e:?} stream failed")))?;
        }
        Ok(())
    }

    fn receive(&mut self, port: Port, buf: &mut [u8]) -> Result<usize, SimError> {
        let from = &mut self.pipe(port).from_companion;
        let n = buf.len().min(from.len());
        for (slot, byte) in buf.iter_mut().zip(from.drain(..n)) {
            *slot = byte;
        }
        if n == 0 {
            // Nothing will come until the simulator sends something: do not spin.
            std::thread::sleep(Duration::from_millis(1));
        }
        Ok(n)
    }

    fn check_alive(&mut self) -> Result<(), SimError> {
        Ok(())
    }

    fn name(&self) -> &'static str {
        "in-process"
    }
}
