//! The firmware's configuration of the core's [`Companion`](companion::Companion): its capacity,
//! the buffers it works in (one `static` [`Storage`], carved for the mission's grid at start),
//! the explorer's and the companion's settings. Everything that happens between the two UARTs
//! is [`harmonic_core::companion`]'s; the board (`board`) gives it byte streams, a clock and a
//! watchdog.
//!
//! The firmware is built with a voxel capacity ([`CAPACITY`]), not a grid: at mission start
//! the grid's dimensions, origin and resolution come over the depth link
//! ([`companion::GeometryWait`]); a grid within capacity ([`fits`]) is taken and the storage
//! carved for it ([`build_explorer`]); a larger one is refused with both numbers.

use core::mem::MaybeUninit;

use harmonic_core::companion::{self, CompanionConfig};
use harmonic_core::domain::Label;
use harmonic_core::downlink::{Resource, Shortfall};
use harmonic_core::explore::{ConfigError, Explorer, ExplorerConfig, ExplorerStorage};
use harmonic_core::map::{touched_words, MapGeometry};
use harmonic_core::mavlink::BridgeConfig;
use harmonic_core::signing::SecretKey;
use harmonic_core::solve::multigrid::scratch_size;
use harmonic_core::solve::Bf16;

pub use harmonic_core::companion::{Event, IoError, Phase};

/// The firmware's companion: the core's, with the firmware's link decoder and signing streams.
pub type Firmware<'a> = companion::Companion<'a, LINK_DECODER_BYTES, SIGNING_STREAMS>;

/// Voxels of the largest grid the firmware maps, of any shape (64 × 64 × 32 is one; so are
/// 70 × 40 × 40 and 60 × 80 × 25). A multiple of 32 (the touched bits are words).
pub const CAPACITY: usize = 131_072;
/// Cells of the multigrid's coarse levels the firmware has room for: a sixth of
/// [`CAPACITY`]. The levels halve each axis (rounding up), so a grid needs about a seventh of
/// its voxels (18 724 for 64 × 64 × 32, 18 068 for 60 × 80 × 25); a grid thin enough to need
/// more is refused with both numbers.
pub const COARSE_CAPACITY: usize = CAPACITY / 6;
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
/// Sized by [`CAPACITY`] and [`COARSE_CAPACITY`]; [`build_explorer`] carves what the mission's
/// grid needs from the front of each pool.
pub struct Storage {
    log_odds: [i8; CAPACITY],
    touched: [u32; CAPACITY / 32],
    labels: [Label; CAPACITY],
    phi: [f32; CAPACITY],
    queue: [u32; QUEUE_LEN],
    /// bfloat16: half the bytes of `f32` (see `harmonic_core::solve::multigrid::CoarseValues`).
    coarse_values: [Bf16; 2 * COARSE_CAPACITY],
    coarse_labels: [Label; COARSE_CAPACITY],
    depth: [u16; MAX_DEPTH_PIXELS],
}

impl Storage {
    /// All zeros.
    pub const fn new() -> Self {
        Self {
            log_odds: [0; CAPACITY],
            touched: [0; CAPACITY / 32],
            labels: [Label::Outside; CAPACITY],
            phi: [0.0; CAPACITY],
            queue: [0; QUEUE_LEN],
            coarse_values: [Bf16::ZERO; 2 * COARSE_CAPACITY],
            coarse_labels: [Label::Outside; COARSE_CAPACITY],
            depth: [0; MAX_DEPTH_PIXELS],
        }
    }
}

impl Default for Storage {
    fn default() -> Self {
        Self::new()
    }
}

/// Whether the firmware can map `geometry`: at most [`CAPACITY`] voxels and
/// [`COARSE_CAPACITY`] coarse cells; otherwise what runs short, with both numbers.
pub fn fits(geometry: &MapGeometry) -> Result<(), Shortfall> {
    let dims = geometry.dims();
    let short = |what, needed: usize, capacity: usize| Shortfall {
        what,
        needed: u32::try_from(needed).unwrap_or(u32::MAX),
        capacity: u32::try_from(capacity).unwrap_or(u32::MAX),
    };
    if dims.len() > CAPACITY {
        return Err(short(Resource::Voxels, dims.len(), CAPACITY));
    }
    let coarse = scratch_size(&dims).labels;
    if coarse > COARSE_CAPACITY {
        return Err(short(Resource::CoarseCells, coarse, COARSE_CAPACITY));
    }
    Ok(())
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

/// Builds the explorer of `geometry` over `storage` (the front of each pool, as much as the
/// grid needs; a grid that does not [`fit`](fits) is refused, `StorageTooSmall`), in place in
/// `slot` (a `static` on the MCU), and returns it with the depth-image buffer. Its own
/// function, so its stack frame (the explorer under construction) is gone before the rest of
/// the firmware is built.
#[inline(never)]
pub fn build_explorer<'a>(
    storage: &'a mut Storage,
    geometry: MapGeometry,
    slot: &'a mut MaybeUninit<Explorer<'a>>,
) -> Result<(&'a mut Explorer<'a>, &'a mut [u16]), ConfigError> {
    fits(&geometry).map_err(|_| ConfigError::StorageTooSmall)?;
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
    let dims = geometry.dims();
    let (n, coarse) = (dims.len(), scratch_size(&dims));
    let too_small = ConfigError::StorageTooSmall;
    let explorer = Explorer::new_in(
        slot,
        geometry,
        explorer_config(),
        ExplorerStorage {
            log_odds: log_odds.get_mut(..n).ok_or(too_small)?,
            touched: touched.get_mut(..touched_words(&dims)).ok_or(too_small)?,
            labels: labels.get_mut(..n).ok_or(too_small)?,
            phi: phi.get_mut(..n).ok_or(too_small)?,
            queue,
            coarse_values: coarse_values.get_mut(..coarse.values).ok_or(too_small)?.into(),
            coarse_labels: coarse_labels.get_mut(..coarse.labels).ok_or(too_small)?,
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

    fn grid(nx: usize, ny: usize, nz: usize) -> MapGeometry {
        let dims = harmonic_core::map::Dims::new(nx, ny, nz).unwrap();
        MapGeometry::new(dims, nalgebra::Point3::origin(), 0.1).unwrap()
    }

    #[test]
    fn grids_of_any_shape_within_capacity_fit_and_larger_ones_are_refused_with_both_numbers() {
        // The old fixed box, s1, the apartment and the garage fit.
        for (nx, ny, nz) in [(64, 64, 32), (70, 40, 40), (60, 80, 25), (70, 90, 20)] {
            assert_eq!(fits(&grid(nx, ny, nz)), Ok(()), "{nx}×{ny}×{nz}");
        }
        // The office does not: 240 000 voxels.
        assert_eq!(
            fits(&grid(120, 80, 25)),
            Err(Shortfall {
                what: Resource::Voxels,
                needed: 240_000,
                capacity: CAPACITY as u32
            })
        );
        // Within capacity, but so thin that the coarse levels need more than a sixth.
        let thin = fits(&grid(2048, 63, 1)).unwrap_err();
        assert_eq!(thin.what, Resource::CoarseCells);
        assert!(thin.needed > thin.capacity);
        // The whole state must leave room for the stack in 1 MiB.
        assert!(core::mem::size_of::<Storage>() < 1000 * 1024);
    }

    #[test]
    fn the_explorer_is_built_for_the_grid_that_came_and_refuses_one_over_capacity() {
        let mut storage = Box::new(Storage::new());
        let mut slot = Box::new(MaybeUninit::uninit());
        let (explorer, depth) = build_explorer(&mut storage, grid(70, 40, 40), &mut slot).unwrap();
        assert_eq!(explorer.map().geometry().dims().len(), 112_000);
        assert_eq!(depth.len(), MAX_DEPTH_PIXELS);
        let mut storage = Box::new(Storage::new());
        let mut slot = Box::new(MaybeUninit::uninit());
        assert_eq!(
            build_explorer(&mut storage, grid(120, 80, 25), &mut slot).err(),
            Some(ConfigError::StorageTooSmall)
        );
    }
}
