//! The firmware's configuration of the core's [`Companion`](companion::Companion): the grid, the buffers it works in
//! (one `static` [`Storage`]), the explorer's and the companion's settings. Everything that
//! happens between the two UARTs is [`harmonic_core::companion`]'s; the board (`board`) gives
//! it byte streams, a clock and a watchdog.

use core::mem::MaybeUninit;

use harmonic_core::companion::{self, CompanionConfig};
use harmonic_core::domain::Label;
use harmonic_core::explore::{ConfigError, Explorer, ExplorerConfig, ExplorerStorage};
use harmonic_core::map::{Dims, MapError, MapGeometry};
use harmonic_core::mavlink::BridgeConfig;
use harmonic_core::signing::SecretKey;
use harmonic_core::solve::Bf16;
use nalgebra::Point3;

pub use harmonic_core::companion::{Event, IoError, Phase};

/// The firmware's companion: the core's, with the firmware's link decoder and signing streams.
pub type Firmware<'a> = companion::Companion<'a, LINK_DECODER_BYTES, SIGNING_STREAMS>;

/// Voxels along x of the firmware's grid.
pub const NX: usize = 64;
/// Voxels along y.
pub const NY: usize = 64;
/// Voxels along z.
pub const NZ: usize = 32;
/// Voxels in the grid.
pub const VOXELS: usize = NX * NY * NZ;
/// Voxel edge, metres: the grid covers 6.4 × 6.4 × 3.2 m.
pub const RESOLUTION: f32 = 0.1;
/// Map-frame position of the grid's minimum corner.
pub const ORIGIN: [f32; 3] = [0.0, 0.0, 0.0];
/// Cells of the multigrid's coarse levels for the grid (32·32·16 + 16·16·8 + 8·8·4 + 4·4·2 +
/// 2·2·1); checked against `scratch_size` when the explorer is built.
pub const COARSE_CELLS: usize = 18_724;
/// Flood-fill queue entries (larger fills sweep, see `harmonic_core::domain`).
pub const QUEUE_LEN: usize = 2048;
/// Largest depth image, pixels.
pub const MAX_DEPTH_PIXELS: usize = 100 * 100;
/// Bytes of the depth link's frame decoder: one chunk of 10 rows of a 100-pixel-wide image.
pub const LINK_DECODER_BYTES: usize = 2048;
/// Link speed of both UARTs, baud (8N1).
pub const BAUD: u32 = 921_600;
/// Resend requests per depth image at most; then the image is taken with the rows that came
/// (as `harmonic-sim --link-arq-rounds` defaults to).
pub const ARQ_ROUNDS: u8 = 4;

/// After a complete exploration the firmware flies home, as `harmonic-sim explore` does by
/// default; false holds where the exploration ended.
pub const RETURN_HOME_AFTER_COMPLETE: bool = true;
/// MAVLink 2 signing key shared with the autopilot (64 hex digits), taken from the build
/// environment: `HARMONIC_FW_MAVLINK_KEY=$(cat key.hex) cargo build -p harmonic-fw …`. With a
/// key every frame the firmware sends is signed and only frames the key signed are acted on
/// (see [`harmonic_core::signing`]); without one, neither. A key that is not 64 hex digits
/// fails the build.
pub const MAVLINK_KEY: Option<SecretKey> = match option_env!("HARMONIC_FW_MAVLINK_KEY") {
    Some(hex) => Some(built_in_key(hex)),
    None => None,
};
/// Signing streams (system, component, link) the firmware's verifier tells apart: the
/// autopilot, a ground station or two, and room to spare.
pub const SIGNING_STREAMS: usize = 8;

/// The built-in key, read at compile time for [`MAVLINK_KEY`] by the same parser as
/// `--mavlink-key` files ([`SecretKey::from_hex`]); a bad one stops the build.
#[allow(
    clippy::panic,
    reason = "evaluated only for the MAVLINK_KEY constant: the panic is a build error naming the variable"
)]
const fn built_in_key(hex: &str) -> SecretKey {
    match SecretKey::from_hex(hex) {
        Ok(key) => key,
        Err(_) => panic!("HARMONIC_FW_MAVLINK_KEY: not 64 hex digits"),
    }
}

/// Everything the explorer and the link work in; lives in one `static` on the MCU. Zeroed
/// (`.bss`): the explorer initialises what it needs.
pub struct Storage {
    log_odds: [i8; VOXELS],
    touched: [u32; VOXELS / 32],
    labels: [Label; VOXELS],
    phi: [f32; VOXELS],
    queue: [u32; QUEUE_LEN],
    /// bfloat16: 73 KiB instead of 146 KiB (see `harmonic_core::solve::multigrid::CoarseValues`).
    coarse_values: [Bf16; 2 * COARSE_CELLS],
    coarse_labels: [Label; COARSE_CELLS],
    depth: [u16; MAX_DEPTH_PIXELS],
}

impl Storage {
    /// All zeros.
    pub const fn new() -> Self {
        Self {
            log_odds: [0; VOXELS],
            touched: [0; VOXELS / 32],
            labels: [Label::Outside; VOXELS],
            phi: [0.0; VOXELS],
            queue: [0; QUEUE_LEN],
            coarse_values: [Bf16::ZERO; 2 * COARSE_CELLS],
            coarse_labels: [Label::Outside; COARSE_CELLS],
            depth: [0; MAX_DEPTH_PIXELS],
        }
    }
}

impl Default for Storage {
    fn default() -> Self {
        Self::new()
    }
}

/// The firmware's map geometry. (The constants are valid, so this is `Ok`; a port that edits
/// them gets the reason at boot instead of a panic.)
pub fn geometry() -> Result<MapGeometry, MapError> {
    MapGeometry::new(Dims::new(NX, NY, NZ)?, Point3::from(ORIGIN), RESOLUTION)
}

/// The explorer configuration: the host's defaults, with plain V-cycles (no Krylov storage
/// fits) and a cap on cycles so one plan stays bounded.
pub fn explorer_config() -> ExplorerConfig {
    let mut config = ExplorerConfig::default();
    config.solve.max_iterations = 400;
    // The `cold-start` feature measures cold solves (fw-budget): every solve from ψ = 0.
    config.solve.warm_start = !cfg!(feature = "cold-start");
    config
}

/// The companion configuration: the bridge's defaults, [`ARQ_ROUNDS`],
/// [`RETURN_HOME_AFTER_COMPLETE`], [`MAVLINK_KEY`], no look-around, and a clock of `tick_hz`.
pub fn companion_config(tick_hz: u32) -> CompanionConfig {
    CompanionConfig {
        bridge: BridgeConfig::default(),
        arq_rounds: ARQ_ROUNDS,
        return_home_after_complete: RETURN_HOME_AFTER_COMPLETE,
        tick_hz,
        signing_key: MAVLINK_KEY,
        // The processor-in-the-loop runs plan from the first scan (pil-small's recorded run).
        look_around: 0,
    }
}

/// The firmware around `explorer` (see [`build_explorer`]) and the depth-image buffer, with
/// [`companion_config`], built in place in `slot` (a `static` on the MCU); `tick_hz` is the
/// rate of the clock later passed to [`Firmware::poll`]. Its own function, as
/// [`build_explorer`] is: the companion under construction (about 6 KiB) lives in this frame,
/// gone before the loop starts, and not in the frame of the loop's caller for good.
#[inline(never)]
pub fn build_firmware<'a>(
    explorer: &'a mut Explorer<'a>,
    depth: &'a mut [u16],
    tick_hz: u32,
    slot: &'a mut MaybeUninit<Firmware<'a>>,
) -> Result<&'a mut Firmware<'a>, ConfigError> {
    Ok(slot.write(Firmware::new(explorer, depth, companion_config(tick_hz))?))
}

/// Builds the explorer over `storage`, in place in `slot` (a `static` on the MCU), and returns
/// it with the depth-image buffer. Its own function, so its stack frame (the explorer under
/// construction) is gone before the rest of the firmware is built.
#[inline(never)]
pub fn build_explorer<'a>(
    storage: &'a mut Storage,
    slot: &'a mut MaybeUninit<Explorer<'a>>,
) -> Result<(&'a mut Explorer<'a>, &'a mut [u16]), ConfigError> {
    let Storage {
        log_odds,
        touched,
        labels,
        phi,
        queue,
        coarse_values,
        coarse_labels,
        depth,
    } = storage;
    let explorer = Explorer::new_in(
        slot,
        geometry().map_err(ConfigError::Map)?,
        explorer_config(),
        ExplorerStorage {
            log_odds,
            touched,
            labels,
            phi,
            queue,
            coarse_values: coarse_values.as_mut_slice().into(),
            coarse_labels,
            // No face conductances: 73 KiB the 1 MiB budget does not have (see
            // `MultigridStorage::faces`); coarse levels use the label-only operator.
            coarse_faces: &mut [],
            krylov: &mut [],
            // 128 KiB more than the budget has: sweeps test the labels instead.
            masks: &mut [],
            surface: &mut [],
            // The thesis's Jacobi solve is a host-side ablation.
            jacobi: &mut [],
            // No room for a box (half a grid's labels and values): whole-grid re-solves.
            local_labels: &mut [],
            local_psi: &mut [],
            flat: &mut [],
        },
    )?;
    Ok((explorer, depth))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_build_time_key_reads_as_hex() {
        let key = built_in_key("  000102030405060708090a0b0c0d0e0f101112131415161718191A1B1C1D1E1F\n");
        let mut bytes = [0u8; 32];
        bytes.iter_mut().enumerate().for_each(|(i, b)| *b = i as u8);
        assert_eq!(key.as_bytes(), &bytes);
    }

    #[test]
    fn the_grid_fits_the_multigrid_scratch_and_the_budget() {
        let g = geometry().unwrap();
        let need = harmonic_core::solve::multigrid::scratch_size(&g.dims());
        assert_eq!(need.values, 2 * COARSE_CELLS);
        assert_eq!(need.labels, COARSE_CELLS);
        assert_eq!(
            harmonic_core::map::touched_words(&g.dims()),
            VOXELS / 32,
            "touched bitset"
        );
        // The whole state must leave room for the stack in 1 MiB.
        assert!(core::mem::size_of::<Storage>() < 1000 * 1024);
    }
}
