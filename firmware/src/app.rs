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
use harmonic_core::map::{touched_words, Dims, MapError, MapGeometry};
use harmonic_core::mavlink::BridgeConfig;
use harmonic_core::signing::SecretKey;
use harmonic_core::solve::multigrid::scratch_size;
use harmonic_core::solve::Bf16;

pub use harmonic_core::companion::{Event, IoError, Phase};

/// The firmware's companion: the core's, with the firmware's link decoder and signing streams.
pub type Firmware<'a> = companion::Companion<'a, LINK_DECODER_BYTES, SIGNING_STREAMS>;

/// Voxels of the largest grid the firmware maps, of any shape (the office's 120 × 80 × 25 and
/// two-level's 80 × 80 × 50 are within it). A multiple of 32 (the touched bits are words).
pub const CAPACITY: usize = 458_752;
/// The firmware plans on cells of 2 × 2 × 2 voxels pooled from the map
/// ([`ExplorerConfig::plan_coarsening`]): an eighth of the planning memory and work of a field
/// over every voxel, which is what lets a building's grid fit 1 MiB and a plan its instruction
/// budget.
pub const PLAN_COARSENING: u8 = 2;
/// Planning cells the firmware has room for: an eighth of [`CAPACITY`] and 6.7 % more for the
/// axes a coarser grid rounds up (the office needs 31 200 for its 240 000 voxels, two-level
/// 40 000 for 320 000). A multiple of 32.
pub const PLAN_CAPACITY: usize = 61_184;
/// Cells of the multigrid's coarse levels over the planning grid the firmware has room for: a
/// sixth of [`PLAN_CAPACITY`]. The levels halve each axis (rounding up), so a grid needs about
/// a seventh of its cells; a grid thin enough to need more is refused with both numbers.
pub const COARSE_CAPACITY: usize = PLAN_CAPACITY / 6;
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
/// Sized by [`CAPACITY`], [`PLAN_CAPACITY`] and [`COARSE_CAPACITY`]; [`build_explorer`] carves
/// what the mission's grid needs from the front of each pool.
pub struct Storage {
    /// The map, one byte per voxel of the mission's grid.
    map_log_odds: [i8; CAPACITY],
    map_touched: [u32; CAPACITY / 32],
    /// The planning grid's pooled map, labels and field.
    log_odds: [i8; PLAN_CAPACITY],
    touched: [u32; PLAN_CAPACITY / 32],
    labels: [Label; PLAN_CAPACITY],
    phi: [f32; PLAN_CAPACITY],
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
            map_log_odds: [0; CAPACITY],
            map_touched: [0; CAPACITY / 32],
            log_odds: [0; PLAN_CAPACITY],
            touched: [0; PLAN_CAPACITY / 32],
            labels: [Label::Outside; PLAN_CAPACITY],
            phi: [0.0; PLAN_CAPACITY],
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

/// Whether the firmware can map `geometry`: at most [`CAPACITY`] voxels, [`PLAN_CAPACITY`]
/// planning cells and [`COARSE_CAPACITY`] multigrid cells; otherwise what runs short, with
/// both numbers.
pub fn fits(geometry: &MapGeometry) -> Result<(), Shortfall> {
    let short = |what, needed: usize, capacity: usize| Shortfall {
        what,
        needed: u32::try_from(needed).unwrap_or(u32::MAX),
        capacity: u32::try_from(capacity).unwrap_or(u32::MAX),
    };
    let voxels = geometry.dims().len();
    if voxels > CAPACITY {
        return Err(short(Resource::Voxels, voxels, CAPACITY));
    }
    let plan =
        planning_dims(geometry).map_err(|_| short(Resource::PlanningCells, usize::MAX, PLAN_CAPACITY))?;
    if plan.len() > PLAN_CAPACITY {
        return Err(short(Resource::PlanningCells, plan.len(), PLAN_CAPACITY));
    }
    let coarse = scratch_size(&plan).labels;
    if coarse > COARSE_CAPACITY {
        return Err(short(Resource::CoarseCells, coarse, COARSE_CAPACITY));
    }
    Ok(())
}

/// The dimensions of the grid the firmware plans on for the mission grid `geometry`.
fn planning_dims(geometry: &MapGeometry) -> Result<Dims, MapError> {
    Ok(geometry.coarsened(usize::from(PLAN_COARSENING))?.dims())
}

/// Instructions one plain V-cycle costs per planning cell on the Cortex-M4F, rounded up: two-level's
/// largest plan under QEMU took 726.2 M in 23 cycles of its 40 000 cells (790 a cell) on
/// `b8c9a4c`, before plans had a budget.
pub const CYCLE_INSTRUCTIONS_PER_CELL: u32 = 800;
/// Instructions a plan's solves may take: the 480 M (1 s at 480 MHz) for a whole plan,
/// less its domain builds and streamline (at most 43 M measured).
pub const SOLVE_INSTRUCTIONS: u32 = 400_000_000;

/// The V-cycles a plan may spend on a planning grid of `cells` cells: [`SOLVE_INSTRUCTIONS`] at
/// [`CYCLE_INSTRUCTIONS_PER_CELL`], at least 4 and at most 400. A plan whose solves reach it
/// traces the field as it stands (a streamline that does not end on a frontier is refused, the
/// vehicle holds) and the next plan resumes the solve from it.
pub fn plan_cycles(cells: usize) -> u32 {
    let per_cycle = u64::from(CYCLE_INSTRUCTIONS_PER_CELL) * cells.max(1) as u64;
    (u64::from(SOLVE_INSTRUCTIONS) / per_cycle).clamp(4, 400) as u32
}

/// The explorer configuration for a planning grid of `cells` cells: the host's defaults, with
/// plain V-cycles (no Krylov storage fits) and a plan's cycles bounded ([`plan_cycles`]).
pub fn explorer_config(cells: usize) -> ExplorerConfig {
    let mut config = ExplorerConfig::default();
    config.solve.max_iterations = plan_cycles(cells);
    // The `cold-start` feature measures cold solves (fw-budget): every solve from ψ = 0.
    config.solve.warm_start = !cfg!(feature = "cold-start");
    config.plan_coarsening = PLAN_COARSENING;
    config
}

/// The companion configuration: the bridge's defaults, [`ARQ_ROUNDS`],
/// [`RETURN_HOME_AFTER_COMPLETE`], [`MAVLINK_KEY`], the simulator's look-around (four
/// headings before the first plan), and a clock of `tick_hz`.
pub fn companion_config(tick_hz: u32) -> CompanionConfig {
    CompanionConfig {
        bridge: BridgeConfig::default(),
        arq_rounds: ARQ_ROUNDS,
        return_home_after_complete: RETURN_HOME_AFTER_COMPLETE,
        tick_hz,
        signing_key: MAVLINK_KEY,
        // As `harmonic-sim explore`: on the coarser planning grid a start that plans from its
        // first view alone leaves more of the big worlds unseen (docs/RESULTS.md).
        look_around: 4,
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
        map_log_odds,
        map_touched,
        log_odds,
        touched,
        labels,
        phi,
        queue,
        coarse_values,
        coarse_labels,
        depth,
    } = storage;
    let dims = planning_dims(&geometry).map_err(ConfigError::Map)?;
    let (n, coarse) = (dims.len(), scratch_size(&dims));
    let fine = geometry.dims();
    let too_small = ConfigError::StorageTooSmall;
    let explorer = Explorer::new_in(
        slot,
        geometry,
        explorer_config(n),
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
            fine_log_odds: map_log_odds.get_mut(..fine.len()).ok_or(too_small)?,
            fine_touched: map_touched.get_mut(..touched_words(&fine)).ok_or(too_small)?,
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

    /// A plan's cycles shrink with the planning grid so its solves stay within the budget:
    /// the office's 60 × 40 × 13 cells get 16, two-level's 40 × 40 × 25 get 12, a full
    /// planning capacity 8, a small room the old 400.
    #[test]
    fn a_plans_cycles_keep_its_solves_within_the_instruction_budget() {
        assert_eq!(plan_cycles(60 * 40 * 13), 16);
        assert_eq!(plan_cycles(40 * 40 * 25), 12);
        assert_eq!(plan_cycles(PLAN_CAPACITY), 8);
        assert_eq!(plan_cycles(500), 400);
        assert_eq!(plan_cycles(0), 400);
        for cells in [1_000, 20_000, PLAN_CAPACITY] {
            let spent = u64::from(plan_cycles(cells)) * u64::from(CYCLE_INSTRUCTIONS_PER_CELL) * cells as u64;
            assert!(spent <= u64::from(SOLVE_INSTRUCTIONS), "{cells}: {spent}");
        }
        assert_eq!(explorer_config(40 * 40 * 25).solve.max_iterations, 12);
    }

    fn grid(nx: usize, ny: usize, nz: usize) -> MapGeometry {
        let dims = harmonic_core::map::Dims::new(nx, ny, nz).unwrap();
        MapGeometry::new(dims, nalgebra::Point3::origin(), 0.1).unwrap()
    }

    #[test]
    fn grids_of_any_shape_within_capacity_fit_and_larger_ones_are_refused_with_both_numbers() {
        // The old fixed box, s1, the apartment, the kitchen, the office and two-level fit.
        for (nx, ny, nz) in [
            (64, 64, 32),
            (70, 40, 40),
            (60, 80, 25),
            (80, 80, 30),
            (120, 80, 25),
            (80, 80, 50),
        ] {
            assert_eq!(fits(&grid(nx, ny, nz)), Ok(()), "{nx}×{ny}×{nz}");
        }
        // s2 does not: 500 000 voxels.
        assert_eq!(
            fits(&grid(100, 100, 50)),
            Err(Shortfall {
                what: Resource::Voxels,
                needed: 500_000,
                capacity: CAPACITY as u32
            })
        );
        // Within capacity, but with axes so odd and thin that the planning grid, rounding each
        // up, needs more cells than an eighth and its margin.
        let thin = fits(&grid(3, 149, 1023)).unwrap_err();
        assert_eq!(
            thin,
            Shortfall {
                what: Resource::PlanningCells,
                needed: 2 * 75 * 512,
                capacity: PLAN_CAPACITY as u32
            }
        );
        // The whole state must leave room for the stack in 1 MiB.
        assert!(core::mem::size_of::<Storage>() < 1000 * 1024);
    }

    #[test]
    fn the_explorer_maps_the_grid_that_came_plans_on_cells_twice_as_large_and_refuses_one_over_capacity() {
        let mut storage = Box::new(Storage::new());
        let mut slot = Box::new(MaybeUninit::uninit());
        let (explorer, depth) = build_explorer(&mut storage, grid(120, 80, 25), &mut slot).unwrap();
        assert_eq!(explorer.observed_map().geometry().dims().len(), 240_000);
        assert_eq!(explorer.map().geometry().dims().len(), 60 * 40 * 13);
        assert_eq!(explorer.map().geometry().resolution(), 0.2);
        assert_eq!(depth.len(), MAX_DEPTH_PIXELS);
        let mut storage = Box::new(Storage::new());
        let mut slot = Box::new(MaybeUninit::uninit());
        assert_eq!(
            build_explorer(&mut storage, grid(100, 100, 50), &mut slot).err(),
            Some(ConfigError::StorageTooSmall)
        );
    }
}
