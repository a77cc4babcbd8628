//! The firmware image: boots, waits on UART0 (the depth link) for the grid the mission maps,
//! builds the explorer for it in a `static`, and runs the loop of [`harmonic_fw::app`] over
//! UART0 and UART1 (MAVLink) forever, feeding the watchdog on every pass. On the host this binary only explains how to build the real one.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]
// As in harmonic-core: no panicking constructs outside tests (README, *No panics*).
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing,
        clippy::unreachable,
        clippy::todo,
        clippy::unimplemented
    )
)]

#[cfg(target_os = "none")]
mod image {
    use core::mem::MaybeUninit;

    use cortex_m_rt::entry;
    use harmonic_core::companion::{GeometryWait, Waited};
    use harmonic_core::explore::Explorer;
    use harmonic_core::map::MapGeometry;
    use harmonic_fw::app::{build_explorer, build_firmware, fits, Event, Firmware, Storage, BAUD, CAPACITY};
    use harmonic_fw::board::timer::Ticks;
    use harmonic_fw::board::uart::{Uart, UART0, UART1};
    use harmonic_fw::board::watchdog::{self, Watchdog};
    use harmonic_fw::board::{halt, PCLK_HZ};

    /// Seconds without a pass of the loop before the watchdog reports a stall (of the board
    /// clock; under QEMU's `-icount shift=0`, 10⁹ instructions per second).
    const WATCHDOG_S: u32 = 60;

    #[entry]
    fn main() -> ! {
        // cortex-m-rt hands this out as `&'static mut`, once: the one place the state lives.
        static mut STORAGE: Storage = Storage::new();
        static mut EXPLORER: MaybeUninit<Explorer<'static>> = MaybeUninit::uninit();
        static mut FIRMWARE: MaybeUninit<Firmware<'static>> = MaybeUninit::uninit();

        // SAFETY: first thing on the main stack; the memory below it is unused.
        unsafe { harmonic_fw::board::stack::paint() };
        // SAFETY: each peripheral is set up once, here, and owned by what it returns.
        let (mut ticks, mut dog, mut link, mut mav) = unsafe {
            (
                Ticks::start(),
                Watchdog::start(WATCHDOG_S),
                Uart::new(UART0, BAUD),
                Uart::new(UART1, BAUD),
            )
        };
        defmt::info!(
            "harmonic-fw: room for {=usize} voxels, state {=usize} bytes; depth link on UART0, MAVLink on UART1; waiting for the grid",
            CAPACITY,
            core::mem::size_of::<Storage>()
        );
        harmonic_fw::board::enable_rx_interrupts(&[&link, &mav]);
        let geometry = wait_for_grid(&mut link, &mut dog);
        let dims = geometry.dims();
        defmt::info!(
            "grid {=usize}x{=usize}x{=usize} at {=f32} m taken",
            dims.nx(),
            dims.ny(),
            dims.nz(),
            geometry.resolution()
        );
        // The firmware's own state (explorer, link decoder, bridge: about 12 KiB) is static too,
        // so the planning stack starts near the top of RAM.
        let built = build_explorer(STORAGE, geometry, EXPLORER)
            .and_then(|(explorer, depth)| build_firmware(explorer, depth, PCLK_HZ, FIRMWARE));
        let firmware = match built {
            Ok(f) => f,
            Err(e) => {
                defmt::error!("explorer refused its configuration: {}", e);
                halt(2)
            }
        };
        defmt::info!(
            "watchdog period {=u32} s; stack used so far {=usize} of {=usize} bytes; waiting for depth frames",
            dog.period_s(),
            harmonic_fw::board::stack::high_water(),
            harmonic_fw::board::stack::room()
        );
        loop {
            dog.feed();
            // Idle in `wfi`, not in a polling loop: a real board saves power, and QEMU gets to
            // deliver the next UART byte (its CMSDK UART does not ask for one when the guest
            // reads; a busy guest under -icount starves the input almost completely).
            harmonic_fw::board::wait_for_input(&[&link, &mav]);
            let phase = |p| {
                watchdog::set_phase(p);
                defmt::debug!("{} from tick {=u64}", p, harmonic_fw::board::timer::now());
            };
            match firmware.poll(&mut link, &mut mav, &mut ticks, phase) {
                Ok(Some(Event::Planned(r))) => {
                    defmt::info!(
                        "frame {=u32}: {} frontier {=u32} interior {=u32} iterations {=u32} ticks integrate {=u64} domain {=u64} solve {=u64} streamline {=u64}",
                        r.frame_id,
                        r.outcome,
                        r.frontier,
                        r.interior,
                        r.solver_iterations,
                        r.integrate_ticks,
                        r.domain_ticks,
                        r.solve_ticks,
                        r.streamline_ticks
                    );
                    defmt::info!(
                        "stack high-water {=usize} of {=usize} bytes",
                        harmonic_fw::board::stack::high_water(),
                        harmonic_fw::board::stack::room()
                    );
                }
                Ok(Some(Event::FrameWithoutPose(id))) => {
                    defmt::warn!("depth frame {=u32} without pose, dropped", id)
                }
                Ok(Some(Event::LinkError(e))) => defmt::warn!("depth link: {}", e),
                Ok(Some(Event::FlightTick(ms))) => defmt::debug!("flight tick at {=u64} ms", ms),
                Ok(None) => {}
                Err(e) => defmt::error!("stream error: {}", e),
            }
        }
    }

    /// Waits on the depth link for a grid the firmware can map, answering each grid that comes
    /// (a refusal names what the grid needs and what the firmware has).
    fn wait_for_grid(link: &mut Uart, dog: &mut Watchdog) -> MapGeometry {
        let mut wait = GeometryWait::new();
        loop {
            dog.feed();
            harmonic_fw::board::wait_for_input(&[&*link]);
            match wait.poll(link, fits) {
                Ok(Waited::Taken(geometry)) => return geometry,
                Ok(Waited::Refused(g, shortfall)) => {
                    let d = g.dims();
                    defmt::warn!(
                        "grid {=usize}x{=usize}x{=usize} refused: {} needed, room for {}",
                        d.nx(),
                        d.ny(),
                        d.nz(),
                        shortfall.needed,
                        shortfall.capacity
                    );
                }
                Ok(Waited::Nothing) => {}
                Err(e) => defmt::error!("stream error: {}", e),
            }
        }
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "harmonic-fw is the Cortex-M4F firmware: build and run it with\n  \
         cargo run -p harmonic-fw --release --target thumbv7em-none-eabihf"
    );
    std::process::exit(2);
}
