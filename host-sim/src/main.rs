//! `harmonic-sim`: explore simulated worlds with the harmonic-core planner.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::str::FromStr;

use clap::{Parser, Subcommand};
use harmonic_core::explore::SolverKind;
use harmonic_core::field::PlanningField;
use harmonic_core::map::Dims;
use harmonic_core::solve::multigrid::Method;
use harmonic_sim::autopilot::{MavlinkConfig, MavlinkSpec};
use harmonic_sim::batch;
use harmonic_sim::bench::{self, BenchSolver};
use harmonic_sim::camera::StereoNoise;
use harmonic_sim::depth_link::{LinkConfig, DEFAULT_ARQ_ROUNDS, DEFAULT_BAUD};
use harmonic_sim::fault::{FaultConfig, DEFAULT_BURST_LEN};
use harmonic_sim::figures::{self, SliceSnapshot};
use harmonic_sim::flight::EmulatorTiming;
use harmonic_sim::npy;
use harmonic_sim::planners::PlannerKind;
use harmonic_sim::problem::{self, SolverChoice};
use harmonic_sim::record::{self, MapSettings, Recorder};
use harmonic_sim::scenario::{builtin_names, Scenario};
use harmonic_sim::sensing::DriftConfig;
use harmonic_sim::sim::{self, Report, SimConfig, StepView};
use harmonic_sim::tlog;
use harmonic_sim::transport::TransportSpec;
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser)]
#[command(
    name = "harmonic-sim",
    version,
    about = "Harmonic-potential exploration simulator"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Fly a simulated multirotor through a world until no reachable frontier is left.
    Explore(Box<ExploreArgs>),
    /// List the built-in scenarios.
    Scenarios,
    /// Benchmark the Laplace solvers on building-like grids (the numbers in BENCHMARKS.md).
    BenchSolve(BenchSolveArgs),
    /// Solve one planning problem from a .npy label grid and print a JSON line of statistics.
    Solve(SolveArgs),
    /// Summarise a MAVLink .tlog: messages per direction and type, with rates.
    Tlog(TlogArgs),
    /// Be the far end of a TCP depth link: send every byte back, as a loopback plug would.
    LinkEcho(LinkEchoArgs),
    /// The firmware's budget: RAM and flash of the image, and instructions per phase measured
    /// under QEMU with -icount shift=0 on a processor-in-the-loop run (BENCHMARKS.md).
    FwBudget(FwBudgetArgs),
    /// Run every planner on every scenario from the same random starts (parallel); write one
    /// CSV row per run and the thesis-style tables. `bench merge` joins shards.
    Bench(BenchArgs),
    /// Integrate a recorded depth sequence (ours, or TUM RGB-D style) through the core and write
    /// the map (map.npy labels, map.ply occupied voxel centres).
    Replay(ReplayArgs),
    /// The fault campaign: explore a scenario once per cell of a matrix of injected faults
    /// (link bit errors, frame loss, bursts, pose drift, sensor dropouts and outliers, a stale
    /// pose stream) over MAVLink, and print completion, collisions and error counters per cell.
    Faults(FaultsArgs),
    /// Match a rectified stereo pair (PNG, grey or RGB) with the core's block matcher and write
    /// the disparity; with --gt, print Middlebury bad-pixel rates.
    Stereo(StereoArgs),
    /// Render a textured stereo pair from a scenario, with ground truth, to try `stereo` on.
    StereoRender(StereoRenderArgs),
    /// Accuracy and speed of the core's matcher on pairs rendered from scenarios
    /// (BENCHMARKS.md); optionally writes the pairs for scripts/stereo_opencv.py.
    BenchStereo(BenchStereoArgs),
}

/// The matcher's settings on the command line.
#[derive(clap::Args, Clone)]
struct MatcherArgs {
    /// Disparities searched: 0..N pixels.
    #[arg(long, default_value_t = 64)]
    ndisp: u16,
    /// Side of each of the five SAD windows (odd, 3-15; the match footprint is 2W-1 pixels).
    #[arg(long, default_value_t = 7)]
    window: u8,
    /// Uniqueness margin, percent (0 turns the test off).
    #[arg(long, default_value_t = 10)]
    uniqueness: u8,
    /// Left-right check tolerance, pixels.
    #[arg(long, default_value_t = 1)]
    lr_max_diff: u8,
    /// No left-right check.
    #[arg(long)]
    no_lr: bool,
    /// Minimum mean horizontal gradient over the centre window, grey levels (0: off).
    #[arg(long, default_value_t = 2)]
    min_texture: u8,
    /// Blobs of at most this many pixels are removed (0: off; default: 1/256 of the image,
    /// 20-2000).
    #[arg(long)]
    speckle_size: Option<u16>,
    /// Prefilter: `dog` (Difference of Gaussians, sigma 1.0 and 1.6 px), `dog:S1:S2`, or `none`.
    #[arg(long, default_value = "dog", value_parser = parse_prefilter)]
    prefilter: harmonic_core::stereo::Prefilter,
}

impl MatcherArgs {
    fn params(&self, width: u16, height: u16) -> harmonic_core::stereo::StereoParams {
        let defaults = harmonic_core::stereo::StereoParams::new(width, height, self.ndisp);
        harmonic_core::stereo::StereoParams {
            window: self.window,
            uniqueness_percent: self.uniqueness,
            lr_max_diff: (!self.no_lr).then_some(self.lr_max_diff),
            min_texture: self.min_texture,
            speckle_size: self.speckle_size.unwrap_or(defaults.speckle_size),
            prefilter: self.prefilter,
            ..defaults
        }
    }
}

fn parse_prefilter(s: &str) -> Result<harmonic_core::stereo::Prefilter, String> {
    use harmonic_core::stereo::Prefilter;
    match s {
        "none" => return Ok(Prefilter::None),
        "dog" => return Ok(Prefilter::DEFAULT_DOG),
        _ => {}
    }
    let bad = || format!("expected `dog`, `dog:SIGMA_SMALL:SIGMA_LARGE` or `none`, got `{s}`");
    let mut parts = s.split(':');
    if parts.next() != Some("dog") {
        return Err(bad());
    }
    let mut sigma = || parts.next().and_then(|v| v.parse::<f32>().ok()).ok_or_else(bad);
    let (sigma_small, sigma_large) = (sigma()?, sigma()?);
    Ok(Prefilter::DoG {
        sigma_small,
        sigma_large,
    })
}

#[derive(clap::Args)]
#[command(
    after_help = "Disparity files (--out, --gt) hold float32 pixels: PFM (.pfm, Middlebury's \
format, little-endian, rows bottom to top) or NumPy (.npy, shape (H, W)). Pixels without a valid \
match are +inf in both formats (Middlebury's convention for unknown disparity; np.isfinite \
selects the valid ones). Ground-truth pixels that are not finite are not evaluated."
)]
struct StereoArgs {
    /// Left (reference) image, PNG; RGB is converted to grey.
    #[arg(long)]
    left: PathBuf,
    /// Right image, PNG, the same size.
    #[arg(long)]
    right: PathBuf,
    /// Output disparity, pixels, .pfm or .npy; +inf where there is no valid match.
    #[arg(long)]
    out: PathBuf,
    /// Ground-truth disparity (.pfm or .npy, pixels): print bad-1.0, bad-2.0 and density.
    #[arg(long)]
    gt: Option<PathBuf>,
    /// Middlebury non-occlusion mask (PNG, 255 = visible in both views): evaluate only there.
    #[arg(long, requires = "gt")]
    mask: Option<PathBuf>,
    #[command(flatten)]
    matcher: MatcherArgs,
}

#[derive(clap::Args)]
struct StereoRenderArgs {
    /// A built-in scenario name or a scenario .toml file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Render from the random free pose this seed draws instead of the scenario's start.
    #[arg(long)]
    start_seed: Option<u64>,
    /// Output directory: left.png, right.png, gt.pfm, gt.npy, mask.png, calib.txt.
    #[arg(long, default_value = "out/stereo-pair")]
    out: PathBuf,
    /// Resolution as a multiple of the 100x100 thesis camera (75 degree FOV).
    #[arg(long, default_value_t = 2)]
    scale: u16,
    /// Baseline, metres.
    #[arg(long, default_value_t = 0.12, value_parser = parse_positive)]
    baseline: f32,
    /// Sensor noise, grey levels (standard deviation).
    #[arg(long, default_value_t = 1.0)]
    pixel_noise: f32,
    /// Random seed for the sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(clap::Args)]
struct BenchStereoArgs {
    /// Scenarios to render pairs in (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "apartment,office,kitchen,garage"
    )]
    scenarios: Vec<String>,
    /// Pairs per scenario, from random free poses (start seeds 1..=N).
    #[arg(long, default_value_t = 5)]
    pairs: u32,
    /// Resolution as a multiple of the 100x100 thesis camera.
    #[arg(long, default_value_t = 2)]
    scale: u16,
    /// Baseline, metres.
    #[arg(long, default_value_t = 0.12, value_parser = parse_positive)]
    baseline: f32,
    /// Timed repetitions of each match (the fastest counts).
    #[arg(long, default_value_t = 3)]
    repeat: u32,
    /// Write every pair (and our disparity, ours.pfm) into DIR/SCENARIO-K/ for
    /// scripts/stereo_opencv.py.
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    matcher: MatcherArgs,
}

fn stereo_match(args: &StereoArgs) -> Result<(), String> {
    use harmonic_sim::stereo as st;
    let (w, h, left) = st::read_png_gray(&args.left)?;
    let (wr, hr, right) = st::read_png_gray(&args.right)?;
    if (w, h) != (wr, hr) {
        return Err(format!("left is {w}x{h}, right is {wr}x{hr}"));
    }
    let params = args.matcher.params(w, h);
    let mut buffers = st::MatcherBuffers::new(&params)?;
    // The first run pays for touching fresh memory; time the second.
    st::match_pair(params, &left, &right, &mut buffers)?;
    let t0 = std::time::Instant::now();
    let (disparity, stats) = st::match_pair(params, &left, &right, &mut buffers)?;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let disparity = st::disparity_to_f32(&disparity);
    st::write_disparity(&args.out, w, h, &disparity)?;
    let n = f64::from(w) * f64::from(h);
    println!(
        "{w}x{h}, {} disparities, window {}: {:.1} ms ({:.2} ns per pixel-disparity); {:.1} % of pixels matched",
        params.num_disparities,
        params.window,
        ms,
        ms * 1e6 / (n * f64::from(params.num_disparities)),
        100.0 * f64::from(stats.valid) / n
    );
    println!(
        "rejected: {} border, {} textureless, {} ambiguous, {} left-right, {} speckle",
        stats.border, stats.textureless, stats.ambiguous, stats.inconsistent, stats.speckles
    );
    println!("disparity: {} (+inf = no match)", args.out.display());
    if let Some(gt_path) = &args.gt {
        let (gw, gh, gt) = st::read_disparity(gt_path)?;
        if (gw, gh) != (w, h) {
            return Err(format!("ground truth is {gw}x{gh}, the images {w}x{h}"));
        }
        let mask = match &args.mask {
            Some(p) => {
                let (mw, mh, m) = st::read_png_gray(p)?;
                if (mw, mh) != (w, h) {
                    return Err(format!("mask is {mw}x{mh}, the images {w}x{h}"));
                }
                Some(m)
            }
            None => None,
        };
        let m = st::StereoMetrics::evaluate(&disparity, &gt, mask.as_deref());
        let region = if mask.is_some() {
            "non-occluded"
        } else {
            "ground-truth"
        };
        println!(
            "bad-1.0 {:.2} %, bad-2.0 {:.2} % of {} valid {region} pixels; density {:.2} % of {}; bad-2.0 with holes counted {:.2} %; mean error {:.3} px",
            m.bad1, m.bad2, m.valid, m.density, m.evaluated, m.bad2_with_holes, m.mean_abs_error
        );
    }
    Ok(())
}

fn stereo_render(args: &StereoRenderArgs) -> Result<(), String> {
    use harmonic_sim::stereo as st;
    use rand::SeedableRng;
    let mut scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    if let Some(seed) = args.start_seed {
        scenario = scenario.with_random_start(seed);
    }
    let rig = st::StereoRig {
        scale: args.scale,
        baseline_m: args.baseline,
        pixel_noise: args.pixel_noise,
        ..st::StereoRig::default()
    };
    let k = rig.render_intrinsics(&harmonic_sim::camera::DepthCamera::default_thesis().intrinsics)?;
    let pose = harmonic_sim::camera::camera_pose(&scenario.start_position, scenario.start_yaw);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let pair = st::render_pair(
        &scenario.world,
        &k,
        &pose,
        rig.baseline_m,
        rig.pixel_noise,
        &mut rng,
    );
    st::write_pair(&args.out, &pair, &k, rig.baseline_m, rig.num_disparities)?;
    let finite: Vec<f32> = pair.disparity.iter().copied().filter(|d| d.is_finite()).collect();
    let max = finite.iter().copied().fold(0.0, f32::max);
    println!(
        "{}: {}x{} pair from ({:.2}, {:.2}, {:.2}) yaw {:.0} deg, fx {:.1} px, baseline {} m; true disparity up to {:.1} px",
        scenario.world.name,
        k.width(),
        k.height(),
        scenario.start_position.x,
        scenario.start_position.y,
        scenario.start_position.z,
        scenario.start_yaw.to_degrees(),
        k.fx(),
        rig.baseline_m,
        max
    );
    let d = args.out.display();
    println!("wrote {d}/left.png, right.png, gt.pfm, gt.npy, mask.png, calib.txt; try");
    println!(
        "  harmonic-sim stereo --left {d}/left.png --right {d}/right.png --gt {d}/gt.pfm --mask {d}/mask.png --out {d}/disp.pfm"
    );
    Ok(())
}

fn bench_stereo(args: &BenchStereoArgs) -> Result<(), String> {
    use harmonic_sim::stereo as st;
    use rand::SeedableRng;
    let camera = harmonic_sim::camera::DepthCamera::default_thesis();
    let rig = st::StereoRig {
        scale: args.scale,
        baseline_m: args.baseline,
        num_disparities: args.matcher.ndisp,
        window: args.matcher.window,
        ..st::StereoRig::default()
    };
    let k = rig.render_intrinsics(&camera.intrinsics)?;
    let params = args.matcher.params(k.width(), k.height());
    let mut buffers = st::MatcherBuffers::new(&params)?;
    let pixels = f64::from(k.width()) * f64::from(k.height());
    let work = pixels * f64::from(params.num_disparities);
    println!(
        "{}x{} px (fx {:.1}), baseline {} m, {} disparities, window {} (footprint {}), prefilter {:?}",
        k.width(),
        k.height(),
        k.fx(),
        rig.baseline_m,
        params.num_disparities,
        params.window,
        2 * u32::from(params.window) - 1,
        params.prefilter
    );
    println!("| scenario | pairs | bad-1.0 % | bad-2.0 % | density % | bad-2.0 with holes % | mean error px | ms per pair | ns per pixel-disparity |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut all: Vec<(st::StereoMetrics, f64)> = Vec::new();
    let row = |name: &str, rows: &[(st::StereoMetrics, f64)]| {
        let n = rows.len().max(1) as f64;
        let mean = |f: &dyn Fn(&st::StereoMetrics) -> f64| rows.iter().map(|(m, _)| f(m)).sum::<f64>() / n;
        let ms = rows.iter().map(|(_, t)| t).sum::<f64>() / n;
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.1} | {:.2} | {:.3} | {:.2} | {:.2} |",
            rows.len(),
            mean(&|m| m.bad1),
            mean(&|m| m.bad2),
            mean(&|m| m.density),
            mean(&|m| m.bad2_with_holes),
            mean(&|m| m.mean_abs_error),
            ms,
            ms * 1e6 / work
        );
    };
    for name in &args.scenarios {
        let base = Scenario::by_name_or_path(name).map_err(|e| e.to_string())?;
        let mut rows = Vec::new();
        for i in 1..=u64::from(args.pairs) {
            let scenario = base.with_random_start(i);
            let pose = harmonic_sim::camera::camera_pose(&scenario.start_position, scenario.start_yaw);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(i);
            let pair = st::render_pair(
                &scenario.world,
                &k,
                &pose,
                rig.baseline_m,
                rig.pixel_noise,
                &mut rng,
            );
            let mut best = f64::INFINITY;
            let mut result = None;
            for _ in 0..args.repeat.max(1) {
                let t0 = std::time::Instant::now();
                let r = st::match_pair(params, &pair.left, &pair.right, &mut buffers)?;
                best = best.min(t0.elapsed().as_secs_f64() * 1e3);
                result = Some(r);
            }
            let Some((disparity, _)) = result else { continue };
            let disparity = st::disparity_to_f32(&disparity);
            let m = st::StereoMetrics::evaluate(&disparity, &pair.disparity, Some(&pair.mask));
            if let Some(out) = &args.out {
                let dir = out.join(format!("{}-{i}", base.world.name));
                st::write_pair(&dir, &pair, &k, rig.baseline_m, params.num_disparities)?;
                st::write_pfm(&dir.join("ours.pfm"), k.width(), k.height(), &disparity)?;
            }
            rows.push((m, best));
        }
        row(&base.world.name, &rows);
        all.extend(rows);
    }
    row("**all**", &all);
    if let Some(out) = &args.out {
        println!(
            "pairs: {}/SCENARIO-K/ (compare: python3 scripts/stereo_opencv.py {})",
            out.display(),
            out.display()
        );
    }
    Ok(())
}

#[derive(clap::Args)]
struct ReplayArgs {
    /// The sequence directory (depth.txt, groundtruth.txt, depth/*.png).
    dir: PathBuf,
    /// Output directory for map.npy and map.ply.
    #[arg(long, default_value = "replay")]
    out: PathBuf,
    /// Intrinsics `fx,fy,cx,cy,width,height` (default: DIR/intrinsics.txt).
    #[arg(long)]
    intrinsics: Option<String>,
    /// Depth units per metre in the PNGs: 1000 (ours, millimetres) or 5000 (TUM RGB-D).
    #[arg(long, default_value_t = 1000.0, value_parser = parse_positive)]
    depth_scale: f32,
    /// Largest time difference (s) between a depth frame and the pose associated with it.
    #[arg(long, default_value_t = 0.02, value_parser = parse_positive)]
    max_time_difference: f32,
}

fn replay_sequence(args: &ReplayArgs) -> Result<(), String> {
    let intrinsics = match &args.intrinsics {
        Some(s) => Some(
            record::parse_intrinsics(&s.split(',').map(|p| p.trim().to_string()).collect::<Vec<_>>())
                .map_err(|e| format!("--intrinsics `{s}`: {e}"))?,
        ),
        None => None,
    };
    let cfg = record::ReplayConfig {
        dir: args.dir.clone(),
        intrinsics,
        map: None,
        depth_scale: args.depth_scale,
        max_time_difference: f64::from(args.max_time_difference),
    };
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;
    let (npy_path, ply_path) = (args.out.join("map.npy"), args.out.join("map.ply"));
    let summary = record::replay(&cfg, |map| {
        figures::write_labels(map, &npy_path)?;
        figures::write_ply(map, &ply_path)
    })?;
    println!("{}", serde_json::to_string(&summary).map_err(|e| e.to_string())?);
    eprintln!(
        "map: {} (labels), {} (occupied voxel centres)",
        npy_path.display(),
        ply_path.display()
    );
    Ok(())
}

#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
struct BenchArgs {
    #[command(subcommand)]
    action: Option<BenchAction>,
    /// `all` (the six thesis scenarios: s1, s2, kitchen, s4, apartment-thesis, garage) or
    /// comma-separated built-in names or scenario files.
    #[arg(long, default_value = "all")]
    scenarios: String,
    /// `all` or comma-separated planner names (see `explore --planner`; `all` leaves out the
    /// `harmonic-thesis` ablation).
    #[arg(long, default_value = "all")]
    planners: String,
    /// Runs (random starts) per scenario and planner.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..))]
    runs: u32,
    /// Seed of the first run; run k uses seed FIRST_SEED + k.
    #[arg(long, default_value_t = 1)]
    first_seed: u64,
    /// Output directory (runs.csv, curves.csv, results.md, coverage_*.png).
    #[arg(long, default_value = "results")]
    out: PathBuf,
    /// Run only shard I of N (jobs k with k mod N = I - 1), to split a sweep across machines.
    #[arg(long, value_parser = batch::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Worker threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    jobs: usize,
    /// Stop a run after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Fly every path to its end before the next scan (the paper's mode).
    #[arg(long)]
    follow_full_path: bool,
    #[command(flatten)]
    sensing: SensingArgs,
    #[command(flatten)]
    field: FieldArgs,
    /// No per-run progress lines.
    #[arg(long)]
    quiet: bool,
}

#[derive(Subcommand)]
enum BenchAction {
    /// Join the runs of several shard directories (or runs*.csv files) into one table.
    Merge(MergeArgs),
}

#[derive(clap::Args)]
struct MergeArgs {
    /// Shard output directories or runs*.csv files.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Where to write the joined runs.csv, curves.csv and results.md.
    #[arg(long)]
    out: PathBuf,
}

fn bench_runs(args: &BenchArgs) -> Result<(), String> {
    if let Some(BenchAction::Merge(m)) = &args.action {
        let rows = batch::merge(&m.inputs, &m.out)?;
        eprintln!("bench merge: {} runs into {}", rows.len(), m.out.display());
        print!("{}", batch::markdown(&rows));
        return Ok(());
    }
    let mut sim = SimConfig::default();
    args.sensing.check()?;
    args.sensing.apply(&mut sim);
    args.field.apply(&mut sim);
    sim.max_scans = args.max_scans;
    sim.follow_full_path = args.follow_full_path;
    let planners = PlannerKind::parse_list(&args.planners).map_err(|e| format!("--planners: {e}"))?;
    let cfg = batch::BenchConfig {
        scenarios: batch::parse_scenarios(&args.scenarios)?,
        planners,
        runs: args.runs,
        first_seed: args.first_seed,
        shard: args.shard.unwrap_or((1, 1)),
        jobs: args.jobs,
        sim,
    };
    let rows = batch::run(&cfg, &args.out, args.quiet)?;
    if cfg.shard.1 == 1 {
        print!("{}", batch::markdown(&rows));
    }
    eprintln!("bench: {} runs; {}", rows.len(), args.out.display());
    Ok(())
}

#[derive(clap::Args)]
struct FaultsArgs {
    /// Built-in scenario name or path to a scenario TOML file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Output directory for faults.json and faults.md (created if missing).
    #[arg(long, default_value = "out/faults")]
    out: PathBuf,
    /// Only the cells whose name contains one of these (comma-separated), e.g. `ber,stale`.
    #[arg(long, value_delimiter = ',')]
    cells: Vec<String>,
    /// Stop each run after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Random seed for sensor noise and injected faults.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Vehicle radius in metres: obstacles are inflated by this much for planning.
    #[arg(long, default_value_t = 0.2)]
    vehicle_radius: f32,
    /// Instead of the matrix: one pose-drift cell per rate, mm/s (comma-separated), to find
    /// where collisions start, e.g. `1,2,5,10`.
    #[arg(long, value_delimiter = ',', conflicts_with = "cells")]
    drift_rates: Vec<f32>,
}

#[derive(clap::Args)]
struct LinkEchoArgs {
    /// Listen on HOST:PORT for `explore --link tcp:HOST:PORT` (one connection, then exit).
    #[arg(long, conflicts_with = "connect", required_unless_present = "connect")]
    listen: Option<String>,
    /// Connect to `explore --link tcp-listen:HOST:PORT` instead.
    #[arg(long)]
    connect: Option<String>,
}

fn link_echo(args: &LinkEchoArgs) -> Result<(), String> {
    let stream = match (&args.listen, &args.connect) {
        (Some(addr), _) => {
            let listener = std::net::TcpListener::bind(addr).map_err(|e| format!("--listen {addr}: {e}"))?;
            eprintln!("link-echo: listening on {addr}");
            listener
                .accept()
                .map(|(s, _)| s)
                .map_err(|e| format!("--listen {addr}: {e}"))?
        }
        (None, Some(addr)) => {
            std::net::TcpStream::connect(addr).map_err(|e| format!("--connect {addr}: {e}"))?
        }
        (None, None) => return Err("give --listen HOST:PORT or --connect HOST:PORT".into()),
    };
    let bytes = harmonic_sim::transport::echo(stream).map_err(|e| format!("link-echo: {e}"))?;
    eprintln!("link-echo: {bytes} bytes sent back");
    Ok(())
}

#[derive(clap::Args)]
struct TlogArgs {
    /// The .tlog file (8-byte big-endian µs timestamp before each MAVLink frame).
    file: PathBuf,
    /// Component id whose messages count as sent ("out"): the companion computer's.
    #[arg(long, default_value_t = 191)]
    companion_component: u8,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

fn summarize_tlog(args: &TlogArgs) -> Result<(), String> {
    let bytes = std::fs::read(&args.file).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let records = tlog::read_records(&bytes).map_err(|e| format!("{}: {e}", args.file.display()))?;
    let summary = tlog::summarize(&records, args.companion_component);
    if args.json {
        println!("{}", serde_json::to_string(&summary).map_err(|e| e.to_string())?);
    } else {
        print!("{}", tlog::format_summary(&summary));
    }
    Ok(())
}

#[derive(clap::Args)]
struct FwBudgetArgs {
    /// The firmware ELF (default: build it with cargo).
    #[arg(long)]
    firmware: Option<PathBuf>,
    /// Scenario explored to measure the phases.
    #[arg(long, default_value = "pil-small")]
    scenario: String,
    /// Output directory (report.json and the firmware's log).
    #[arg(long, default_value = "out/fw-budget")]
    out: PathBuf,
    /// The QEMU binary.
    #[arg(long, default_value = "qemu-system-arm")]
    qemu: String,
    /// Only the image sizes; no QEMU run.
    #[arg(long)]
    sizes_only: bool,
    /// A firmware built with `--features cold-start` (every solve from ψ = 0): explores the
    /// same scenario again and reports cold solves on the same planning problems.
    #[arg(long)]
    cold_firmware: Option<PathBuf>,
    /// Instead: the core's stereo matcher on the MCU. Builds firmware/examples/stereo_bench.rs
    /// (a separate image, so the flight firmware's RAM is untouched), runs it under QEMU and
    /// prints instructions per 100x100 frame with 64 disparities.
    #[arg(long)]
    stereo: bool,
}

#[derive(clap::Args)]
struct SolveArgs {
    /// uint8 .npy label grid, shape (NX, NY, NZ), C order: 0 unknown, 1 free, 2 occupied.
    #[arg(long)]
    labels: PathBuf,
    /// Source (vehicle) voxel as X,Y,Z indices.
    #[arg(long, value_parser = parse_voxel)]
    source: [usize; 3],
    /// Solver: `mg` (multigrid-preconditioned CG, the host's), `vc` (plain V-cycles, the
    /// firmware's) or `gs` (Gauss-Seidel reference).
    #[arg(long, default_value = "mg", value_parser = ["mg", "vc", "gs"])]
    solver: String,
    /// Relative-residual tolerance.
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// Most cycles (sweeps for `gs`). A solve stopped here before its own rule says "done"
    /// prints `"converged": false` (and still exits 0).
    #[arg(long, default_value_t = 1_000_000)]
    max_cycles: u32,
    /// Error target: go on until the solve's estimate of its largest error of φ (printed as
    /// `error_estimate`) is at or below this as well as the tolerance; `converged` then means
    /// both were met. Default: the residual alone decides.
    #[arg(long, value_parser = parse_positive)]
    max_error: Option<f32>,
    /// Vehicle radius in metres (obstacles and unknown space are inflated by it).
    #[arg(long, default_value_t = 0.0, value_parser = parse_radius)]
    radius: f32,
    /// Voxel edge in metres (scales the radius).
    #[arg(long, default_value_t = 0.1, value_parser = parse_positive)]
    resolution: f32,
    /// Write φ (float32 .npy, same shape, 0 outside the domain) here.
    #[arg(long)]
    out: Option<PathBuf>,
}

fn parse_voxel(s: &str) -> Result<[usize; 3], String> {
    let n: Vec<usize> = s.split(',').filter_map(|p| p.trim().parse().ok()).collect();
    match (n.as_slice(), s.split(',').count()) {
        ([x, y, z], 3) => Ok([*x, *y, *z]),
        _ => Err(format!("expected three voxel indices X,Y,Z, got `{s}`")),
    }
}

fn solve_problem(args: &SolveArgs) -> Result<(), String> {
    let grid = npy::read_u8_file(&args.labels).map_err(|e| format!("{}: {e}", args.labels.display()))?;
    let request = problem::SolveRequest {
        source: args.source,
        solver: match args.solver.as_str() {
            "gs" => SolverChoice::GaussSeidel,
            "vc" => SolverChoice::VCycle,
            _ => SolverChoice::Multigrid,
        },
        tolerance: args.tol,
        max_cycles: args.max_cycles,
        max_error: args.max_error.unwrap_or(f32::INFINITY),
        radius: args.radius,
        resolution: args.resolution,
    };
    let (phi, summary) =
        problem::solve(&grid, &request).map_err(|e| format!("{}: {e}", args.labels.display()))?;
    if let Some(out) = &args.out {
        std::fs::write(out, npy::write_f32(&phi)).map_err(|e| format!("{}: {e}", out.display()))?;
    }
    println!("{}", serde_json::to_string(&summary).map_err(|e| e.to_string())?);
    Ok(())
}

#[derive(clap::Args)]
struct BenchSolveArgs {
    /// Grid sizes, NXxNYxNZ, comma-separated.
    #[arg(long, default_value = "64x64x32,128x128x64", value_delimiter = ',', value_parser = parse_dims)]
    sizes: Vec<Dims>,
    /// Run the Gauss-Seidel reference only on grids with at most this many voxels (its cost grows
    /// like n^(5/3); the 128×128×64 grid takes many minutes).
    #[arg(long, default_value_t = 200_000)]
    gs_max_voxels: usize,
    /// Repetitions per measurement (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Relative-residual tolerance (the explorer solves the screened field to 1e-5).
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// The field: `laplace` (the seed's, vehicle φ = 1, frontiers φ = 0) or `screened` (the
    /// explorer's default: frontiers u = 1, ∇²u = κ²u with the default 0.33 m decay length at
    /// 0.1 m voxels, the vehicle an ordinary voxel).
    #[arg(long, default_value = "laplace", value_parser = ["laplace", "screened"])]
    field: String,
}

fn parse_dims(s: &str) -> Result<Dims, String> {
    let parts: Vec<&str> = s.split('x').collect();
    let n: Vec<usize> = parts.iter().filter_map(|p| p.parse().ok()).collect();
    match n.as_slice() {
        [x, y, z] if parts.len() == 3 && *x >= 16 && *y >= 16 && *z >= 8 => {
            Dims::new(*x, *y, *z).map_err(|e| format!("`{s}`: {e:?}"))
        }
        _ => Err(format!(
            "expected NXxNYxNZ with NX, NY >= 16 and NZ >= 8, got `{s}`"
        )),
    }
}

/// Imperfect sensing, for `explore` and `bench`.
#[derive(clap::Args, Clone)]
struct SensingArgs {
    /// Sensor noise model: `stereo` (σ = 1 px disparity noise per pixel, then the stereo
    /// pipeline's 5 × 5 median), `stereo:SIGMA_PX` or `stereo:SIGMA_PX:FILTER_PX` (odd median
    /// window, 1 = unfiltered). The core integrates it with the rules of exact depth, up to the
    /// range where the depth error stays small (see `--trusted-range`), or with `--stereo-model`.
    #[arg(long, value_parser = parse_noise)]
    noise: Option<StereoNoise>,
    /// With `--noise` or `--depth-from stereo`: integrate with the core's stereo sensor model
    /// (experimental, see docs/RESULTS.md) — depth error σ_z = z²σ_d/(f·b), misses stop 2σ short
    /// of a return, a return marks a surface only where σ is at most a voxel, a hit/miss vote
    /// per voxel per frame instead of "the hit wins", and depth used to the camera's range.
    #[arg(long)]
    stereo_model: bool,
    /// Range (m) up to which depth is integrated; farther returns only clear free space.
    /// Default with `--noise`: where a 1σ (filtered) disparity error moves the depth by 0.1 m
    /// (one voxel): 1.8 m at σ = 1 px with the 5 × 5 median, 0.9 m unfiltered; 2.8 m with
    /// `--depth-from stereo`. Otherwise, and with `--stereo-model`, the camera's 10 m.
    #[arg(long, value_parser = parse_positive)]
    trusted_range: Option<f32>,
    /// Fraction of pixels (0-1) that return half their true depth (gross matching errors).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    outliers: f64,
    /// Boxes the scenario marks `textureless = true` return no depth.
    #[arg(long)]
    textureless: bool,
    /// Pose drift: random walk per keyframe, `SIGMA_POS_M,SIGMA_YAW_RAD` (e.g. 0.1,0.015).
    #[arg(long, value_parser = parse_drift)]
    drift: Option<DriftConfig>,
    /// Depth source: `camera` (the depth camera, with `--noise` if given) or `stereo` (a
    /// textured stereo pair rendered at each scan, 2x the camera's resolution with a 0.12 m
    /// baseline, matched by the core's block matcher; pixels without a match are unknown, not
    /// free; returns integrated up to `--trusted-range`, default 2.8 m).
    #[arg(long, default_value = "camera", value_parser = ["camera", "stereo"])]
    depth_from: String,
    /// With `--depth-from stereo`: rendering resolution as a multiple of the 100x100 camera.
    #[arg(long, default_value_t = 2)]
    stereo_scale: u16,
    /// With `--depth-from stereo`: the matcher's window (odd, 3-15).
    #[arg(long, default_value_t = 7)]
    stereo_window: u8,
}

/// Settings of the `harmonic` planner's default field (harmonic_core::field).
#[derive(clap::Args)]
struct FieldArgs {
    /// Decay length 1/κ of the screened, frontier-sourced field of `--planner harmonic`, in
    /// metres: how much nearness outweighs frontier size (small: the nearest frontier wins;
    /// large: the largest frontier region wins).
    #[arg(long, value_parser = parse_positive)]
    decay_length: Option<f32>,
    /// The value of the screened field at the vehicle that a lowered κ aims for when the
    /// nearest frontier is far (it accepts down to a tenth of it): the smaller, the longer
    /// the field stays local and visits remnants nearest first (default 1e-4; 1e-2 was the
    /// first setting, see docs/RESULTS.md).
    #[arg(long, value_parser = parse_positive)]
    vehicle_value: Option<f32>,
    /// Look from a distance: the core's goal is the first point of its streamline from which
    /// the frontier is in plain sight within this range (metres); 0 flies up to it.
    #[arg(long)]
    view_range: Option<f32>,
    /// Ablation: closest and random frontier choose their goal by the core's view rule (the
    /// first point of the path from which the frontier is in plain sight within the view
    /// range) instead of the thesis's (fly up to it).
    #[arg(long)]
    baseline_views: bool,
    /// Ablation: the core flies its streamline's own curve instead of pulling it taut through
    /// the safe space (same goal, same frontier).
    #[arg(long)]
    raw_streamline: bool,
}

impl FieldArgs {
    fn apply(&self, cfg: &mut SimConfig) {
        if let (Some(d), PlanningField::Screened(p)) = (self.decay_length, &mut cfg.explorer.field) {
            p.decay_length_m = d;
        }
        if let (Some(u), PlanningField::Screened(p)) = (self.vehicle_value, &mut cfg.explorer.field) {
            p.target_vehicle_value = u.min(0.5);
            p.min_vehicle_value = 0.1 * p.target_vehicle_value;
        }
        if let Some(r) = self.view_range {
            cfg.explorer.view_range_m = r.max(0.0);
        }
        cfg.baseline_views = self.baseline_views;
        if self.raw_streamline {
            cfg.explorer.taut_path = false;
        }
    }
}

impl SensingArgs {
    fn check(&self) -> Result<(), String> {
        if self.stereo_model && self.noise.is_none() && self.depth_from != "stereo" {
            return Err(
                "--stereo-model chooses how noisy depth is integrated: give --noise or --depth-from stereo"
                    .into(),
            );
        }
        if self.depth_from == "stereo" && (self.noise.is_some() || self.outliers > 0.0 || self.textureless) {
            return Err(
                "--noise, --outliers and --textureless model the depth camera; with --depth-from stereo the matcher makes its own errors (textureless boxes render flat)".into(),
            );
        }
        Ok(())
    }

    fn apply(&self, cfg: &mut SimConfig) {
        cfg.camera = cfg.camera.with_noise(self.noise);
        cfg.camera.outliers = self.outliers as f32;
        cfg.camera.textureless = self.textureless;
        cfg.drift = self.drift;
        // Exact depth: no error (the camera's range unless --trusted-range).
        let (sigma_px, baseline_m) = self
            .noise
            .map_or((0.0, 1.0), |n| (n.filtered_sigma_px(), n.baseline_m));
        let fx = cfg.camera.intrinsics.fx();
        sim::integrate_noisy_depth(
            cfg,
            sigma_px,
            fx,
            baseline_m,
            self.trusted_range,
            self.stereo_model,
        );
        if self.depth_from == "stereo" {
            let rig = harmonic_sim::stereo::StereoRig {
                scale: self.stereo_scale,
                window: self.stereo_window,
                ..harmonic_sim::stereo::StereoRig::default()
            };
            sim::use_stereo_depth(cfg, rig, self.trusted_range, self.stereo_model);
        }
    }
}

fn parse_drift(s: &str) -> Result<DriftConfig, String> {
    let bad = || format!("expected SIGMA_POS_M,SIGMA_YAW_RAD (two numbers >= 0), got `{s}`");
    let (p, y) = s.split_once(',').ok_or_else(bad)?;
    let (p, y): (f32, f32) = (
        p.trim().parse().map_err(|_| bad())?,
        y.trim().parse().map_err(|_| bad())?,
    );
    if !(p.is_finite() && y.is_finite() && p >= 0.0 && y >= 0.0) {
        return Err(bad());
    }
    Ok(DriftConfig {
        sigma_position_m: p,
        sigma_yaw_rad: y,
    })
}

#[derive(clap::Args)]
struct ExploreArgs {
    /// A built-in scenario name (see `harmonic-sim scenarios`) or a path to a scenario .toml file.
    #[arg(long, default_value = "apartment")]
    scenario: String,
    /// Output directory for report.json (created if missing).
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    sensing: SensingArgs,
    #[command(flatten)]
    field: FieldArgs,
    /// Random seed for sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Start from the random free pose this seed draws instead of the scenario's start (bench
    /// run k is `--start-seed k --seed k`).
    #[arg(long)]
    start_seed: Option<u64>,
    /// Vehicle radius in metres: obstacles are inflated by this much for planning.
    #[arg(long, default_value_t = 0.2, value_parser = parse_radius)]
    vehicle_radius: f32,
    /// Radius of the vehicle body for collision counting, metres.
    #[arg(long, default_value_t = 0.15, value_parser = parse_positive)]
    body_radius: f32,
    /// Distance flown between scans (receding horizon), metres.
    #[arg(long, default_value_t = 1.0, value_parser = parse_positive)]
    replan_distance: f32,
    /// Fly every streamline to its end before the next scan (the paper's mode).
    #[arg(long)]
    follow_full_path: bool,
    /// Maximum speed, m/s.
    #[arg(long, default_value_t = 1.0, value_parser = parse_positive)]
    max_speed: f32,
    /// Maximum yaw rate, degrees per second.
    #[arg(long, default_value_t = 90.0, value_parser = parse_positive)]
    max_yaw_rate: f32,
    /// Stop after this many scans.
    #[arg(long, default_value_t = 3000)]
    max_scans: u32,
    /// Scans at evenly spaced headings, turning on the spot, before the first plan (0: plan
    /// after the first scan).
    #[arg(long, default_value_t = 4)]
    look_around: u32,
    /// Planner: `harmonic` (the core with its default field, frontier-sourced and screened, on
    /// multigrid; the default), `harmonic-laplace` (the core with the seed's Laplace field,
    /// vehicle φ = 1 and frontiers φ = 0, on multigrid), `harmonic-gs` (the seed's field on the
    /// seed paper's Gauss-Seidel), `harmonic-thesis` (the seed's field solved as the thesis
    /// did: Jacobi from φ = 0 at every plan, stopped when the largest relative change of φ falls
    /// below 1e-4, at most 20 000 sweeps; not in `all`), or a baseline: `closest-frontier`,
    /// `random-frontier`, `info-gain`, `weighted-info-gain`.
    #[arg(long, default_value = "harmonic", value_parser = PlannerKind::from_str)]
    planner: PlannerKind,
    /// Laplace solver of the harmonic planner: `mg` (multigrid, default) or `gs` (the seed
    /// paper's Gauss-Seidel; the same as `--planner harmonic-gs`).
    #[arg(long, default_value = "mg", value_parser = ["mg", "gs"])]
    solver: String,
    /// Relative-residual tolerance of the seed's Laplace solve (`harmonic-laplace`, `harmonic-gs`); the
    /// default screened field solves to its own 1e-5 (harmonic_core::field::ScreenedParams).
    #[arg(long, default_value_t = 1e-6, value_parser = parse_positive)]
    tol: f32,
    /// Write every planning step's problem (labels .npy + source) here, for `harmonic-sim solve`.
    #[arg(long)]
    dump_problem: Option<PathBuf>,
    /// Depth-link transport: `sim` (in-process pipe), `tcp:HOST:PORT` (connect),
    /// `tcp-listen:[HOST:]PORT` (wait for the peer) or `serial:PATH[:BAUD]`. Over TCP and serial
    /// the far end must send the bytes back (echo, loopback plug): both link ends run here.
    #[arg(long, default_value = "sim", value_parser = TransportSpec::from_str)]
    link: TransportSpec,
    /// Depth-link baud rate (10 bits per byte on the wire, in simulated time).
    #[arg(long, default_value_t = DEFAULT_BAUD, value_parser = parse_baud)]
    link_baud: u32,
    /// Link fault: bit error rate (probability per data bit).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_ber: f64,
    /// Link fault: probability that a whole link frame (a depth chunk, pose, ...) is lost.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_drop: f64,
    /// Link fault: probability that a link frame is sent twice.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_dup: f64,
    /// Link fault: probability that a link frame is swapped with the next one.
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_reorder: f64,
    /// Link fault: probability that a byte is lost (receiver overrun).
    #[arg(long, default_value_t = 0.0, value_parser = parse_probability)]
    link_byte_drop: f64,
    /// Link fault: noise bursts, `RATE[:BYTES]`: a burst starts at a byte with probability
    /// RATE and replaces BYTES bytes (default 32) by random ones.
    #[arg(long, value_parser = parse_burst)]
    link_burst: Option<(f64, u32)>,
    /// Depth link: resend requests per image at most (selective retransmission over a return
    /// channel at the same baud rate and with the same faults); 0 turns it off.
    #[arg(long, default_value_t = DEFAULT_ARQ_ROUNDS)]
    link_arq_rounds: u8,
    /// Depth link: rows per depth chunk, fixed (1-10 for the 100-pixel camera). Default: the
    /// camera side adapts it to the bit error rate it infers from what is asked again.
    #[arg(long)]
    link_chunk_rows: Option<u16>,
    /// Fly over MAVLink: `emulator` (the default when no value is given: an in-process
    /// PX4-like flight stack), `udpin:HOST:PORT` or `udpout:HOST:PORT` (a real autopilot or
    /// SITL; MAVProxy's address syntax). The explorer plans from the pose the autopilot reports.
    #[arg(long, num_args = 0..=1, default_missing_value = "emulator", value_parser = MavlinkSpec::from_str)]
    mavlink: Option<MavlinkSpec>,
    /// The emulator also streams ODOMETRY (the bridge then prefers it).
    #[arg(long, requires = "mavlink")]
    odometry: bool,
    /// The emulator's pose stream rate (LOCAL_POSITION_NED + ATTITUDE), Hz; it samples the
    /// vehicle at the simulator's time step, so rates above 1 / --dt run at 1 / --dt.
    #[arg(long, default_value_t = 20.0, requires = "mavlink")]
    emulator_rate: f64,
    /// Milliseconds from the emulator sampling a pose to sending its report.
    #[arg(long, default_value_t = 0, requires = "mavlink")]
    emulator_latency_ms: u64,
    /// The emulator's time_boot_ms when the run starts (it booted this long before).
    #[arg(long, default_value_t = 0, requires = "mavlink")]
    emulator_boot_ms: u64,
    /// The emulator reports velocities and yaw rate as zero.
    #[arg(long, requires = "mavlink")]
    emulator_zero_velocities: bool,
    /// Frames taken while the vehicle yaws faster than this (deg/s, measured from the pose
    /// stream) are refused by the core; 0: no check.
    #[arg(long, default_value_t = 30.0)]
    max_frame_yaw_rate: f32,
    /// Frames whose newest pose sample is older than this (ms) are refused by the core; 0: no
    /// check.
    #[arg(long, default_value_t = 150)]
    max_frame_pose_lag_ms: u32,
    /// Record every MAVLink frame both ways in this .tlog file (QGroundControl/MAVProxy format).
    #[arg(long, requires = "mavlink")]
    tlog: Option<PathBuf>,
    /// MAVLink 2 message signing: a file holding the 32-byte secret key as 64 hex digits. The
    /// bridge signs every frame it sends and acts only on frames signed with the key (newer
    /// than the last on their stream, at most a minute old); the rest are counted in
    /// report.json (`mavlink.bridge_signing`). The emulator then requires signing too.
    #[arg(long, requires = "mavlink")]
    mavlink_key: Option<PathBuf>,
    /// Where the planning runs: `host` (the core in this process) or `qemu` (the firmware,
    /// harmonic-fw, on an emulated Cortex-M4F: processor in the loop; see `pil` in the docs).
    #[arg(long, default_value = "host", value_parser = ["host", "qemu"])]
    core: String,
    /// With `--core qemu`: the firmware ELF to run (default: build it with cargo).
    #[arg(long)]
    firmware: Option<PathBuf>,
    /// With `--core qemu`: the QEMU binary.
    #[arg(long, default_value = "qemu-system-arm")]
    qemu: String,
    /// Write figures into the output directory: slice.png (occupancy, φ, descent directions and
    /// the chosen path in the horizontal slice through the vehicle), top_view.png (the flown path
    /// over the final map) and coverage.png.
    #[arg(long)]
    figures: bool,
    /// The step whose plan slice.png shows (the first full plan at or after it; default: a
    /// third of the way through the run).
    #[arg(long, requires = "figures")]
    figure_step: Option<u32>,
    /// Record every integrated depth frame and its pose in DIR, TUM RGB-D style (16-bit PNG in
    /// mm, depth.txt, groundtruth.txt) for `harmonic-sim replay`.
    #[arg(long)]
    record: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn parse_baud(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(v) if v > 0 => Ok(v),
        _ => Err(format!("expected a baud rate (a positive integer), got `{s}`")),
    }
}

fn parse_probability(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a probability between 0 and 1, got `{s}`")),
    }
}

fn parse_burst(s: &str) -> Result<(f64, u32), String> {
    let (rate, len) = match s.split_once(':') {
        Some((r, l)) => (r, Some(l)),
        None => (s, None),
    };
    let rate = parse_probability(rate).map_err(|e| format!("`{s}`: {e} (RATE[:BYTES])"))?;
    let len = match len {
        None => DEFAULT_BURST_LEN,
        Some(l) => match l.parse::<u32>() {
            Ok(n) if n > 0 => n,
            _ => {
                return Err(format!(
                    "`{s}`: burst length `{l}` is not a positive number of bytes"
                ))
            }
        },
    };
    Ok((rate, len))
}

fn parse_positive(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got `{s}`")),
    }
}

fn parse_radius(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && (0.0..=0.6).contains(&v) => Ok(v),
        _ => Err(format!("expected a radius between 0 and 0.6 m, got `{s}`")),
    }
}

fn parse_noise(s: &str) -> Result<StereoNoise, String> {
    let mut parts = s.split(':');
    let kind = parts.next().unwrap_or("");
    if kind != "stereo" {
        return Err(format!(
            "unknown noise model `{kind}` (expected `stereo`, `stereo:SIGMA_PX` or `stereo:SIGMA_PX:FILTER_PX`)"
        ));
    }
    let mut noise = StereoNoise::default();
    if let Some(v) = parts.next() {
        noise.sigma_px = match v.parse::<f32>() {
            Ok(x) if x.is_finite() && x >= 0.0 => x,
            _ => {
                return Err(format!(
                    "bad disparity sigma `{v}` (expected a number of pixels ≥ 0)"
                ))
            }
        };
    }
    if let Some(w) = parts.next() {
        noise.filter_px = match w.parse::<u8>() {
            Ok(x) if x % 2 == 1 && x <= 15 => x,
            _ => {
                return Err(format!(
                    "bad median window `{w}` (expected an odd number of pixels from 1 to 15; 1 = no filter)"
                ))
            }
        };
    }
    if parts.next().is_some() {
        return Err(format!("`{s}`: too many fields (stereo[:SIGMA_PX[:FILTER_PX]])"));
    }
    Ok(noise)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Scenarios => {
            for name in builtin_names() {
                println!("{name}");
            }
            Ok(())
        }
        Command::Explore(args) => explore(*args),
        Command::Solve(args) => solve_problem(&args),
        Command::Tlog(args) => summarize_tlog(&args),
        Command::LinkEcho(args) => link_echo(&args),
        Command::FwBudget(args) => fw_budget(&args),
        Command::Bench(args) => bench_runs(&args),
        Command::Replay(args) => replay_sequence(&args),
        Command::Faults(args) => fault_campaign(&args),
        Command::Stereo(args) => stereo_match(&args),
        Command::StereoRender(args) => stereo_render(&args),
        Command::BenchStereo(args) => bench_stereo(&args),
        Command::BenchSolve(args) => {
            bench_solve(&args);
            Ok(())
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn explore(args: ExploreArgs) -> Result<(), String> {
    let mut scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    if let Some(seed) = args.start_seed {
        scenario = scenario.with_random_start(seed);
    }
    let mut cfg = SimConfig::default();
    args.sensing.check()?;
    args.sensing.apply(&mut cfg);
    args.field.apply(&mut cfg);
    cfg.seed = args.seed;
    cfg.planner = args.planner;
    cfg.explorer.vehicle_radius = args.vehicle_radius;
    cfg.explorer.solve.tolerance = args.tol;
    cfg.explorer.solver = if args.solver == "gs" {
        SolverKind::GaussSeidel
    } else {
        SolverKind::Multigrid
    };
    cfg.body_radius = args.body_radius;
    cfg.replan_distance = args.replan_distance;
    cfg.follow_full_path = args.follow_full_path;
    cfg.max_speed = args.max_speed;
    cfg.max_yaw_rate = args.max_yaw_rate.to_radians();
    cfg.max_scans = args.max_scans;
    cfg.look_around = args.look_around;
    cfg.explorer.max_frame_yaw_rate = args.max_frame_yaw_rate.to_radians();
    cfg.explorer.max_frame_pose_lag_ms = args.max_frame_pose_lag_ms;
    cfg.dump_problem = args.dump_problem.clone();
    let (burst_rate, burst_len) = args.link_burst.unwrap_or((0.0, DEFAULT_BURST_LEN));
    cfg.link = LinkConfig {
        transport: args.link.clone(),
        baud: args.link_baud,
        faults: FaultConfig {
            bit_error_rate: args.link_ber,
            byte_drop: args.link_byte_drop,
            frame_drop: args.link_drop,
            frame_duplicate: args.link_dup,
            frame_reorder: args.link_reorder,
            burst_rate,
            burst_len,
        },
        arq_rounds: args.link_arq_rounds,
        chunk_rows: args.link_chunk_rows,
    };
    if !(args.emulator_rate.is_finite() && args.emulator_rate > 0.0) {
        return Err(format!(
            "--emulator-rate {}: must be a positive number of Hz",
            args.emulator_rate
        ));
    }
    let signing_key = args
        .mavlink_key
        .as_ref()
        .map(|path| {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("--mavlink-key {}: {e}", path.display()))?;
            harmonic_core::signing::SecretKey::from_hex(&text).map_err(|_| {
                format!(
                    "--mavlink-key {}: expected the 32-byte key as 64 hex digits",
                    path.display()
                )
            })
        })
        .transpose()?;
    cfg.mavlink = args.mavlink.clone().map(|spec| MavlinkConfig {
        spec,
        odometry: args.odometry,
        emulator: EmulatorTiming {
            pose_period_ms: ((1000.0 / args.emulator_rate).round() as u64).max(1),
            latency_ms: args.emulator_latency_ms,
            boot_ms: args.emulator_boot_ms,
            zero_velocities: args.emulator_zero_velocities,
        },
        tlog: args.tlog.clone(),
        signing_key: signing_key.clone(),
        ..MavlinkConfig::default()
    });
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;

    // On a terminal: a live status line. Elsewhere (CI logs, pipes): a plain line every 25 steps.
    let tty = std::io::stderr().is_terminal();
    let bar = if args.quiet || !tty {
        ProgressBar::hidden()
    } else {
        ProgressBar::new_spinner()
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    let mut scans = 0u32;
    let on_step = |s: &sim::StepRecord| {
        scans += s.frames_integrated;
        // Steps whose frame was lost on the link are counted apart from scans.
        let lost = if s.step > scans {
            format!(" ({} steps)", s.step)
        } else {
            String::new()
        };
        let line = format!(
            "scans {:>4}{lost}  coverage {:>5.1}%  frontier {:>5}  path {:>6.1} m  {}",
            scans,
            s.coverage_free * 100.0,
            s.frontier,
            s.path_length_m,
            match s.outcome.as_str() {
                "kept" => "goal kept".to_string(),
                "no_frame" => "no frame".to_string(),
                _ => format!("solve {:>7.1} ms", s.solve_ms),
            }
        );
        if !args.quiet && !tty && s.step.is_multiple_of(25) {
            eprintln!("{line}");
        }
        bar.set_message(line);
        bar.tick();
    };
    if args.core == "qemu" && (args.figures || args.record.is_some()) {
        return Err("--figures and --record need --core host".into());
    }
    let geometry = sim::scenario_geometry(&scenario).map_err(|e| e.to_string())?;
    let mut recorder = match &args.record {
        Some(dir) => {
            let lo = cfg.explorer.log_odds;
            let settings = MapSettings {
                origin: geometry.origin().coords.into(),
                dims: [geometry.dims().nx(), geometry.dims().ny(), geometry.dims().nz()],
                resolution: geometry.resolution(),
                log_odds: [lo.hit, lo.miss, lo.min, lo.max],
                min_range: cfg.explorer.integration.min_range,
                max_range: cfg.explorer.integration.max_range,
                vehicle_radius: cfg.explorer.vehicle_radius,
            };
            Some(Recorder::create(dir, &settings)?)
        }
        None => None,
    };
    let mut snapshots: Vec<SliceSnapshot> = Vec::new();
    let mut observe_error: Option<String> = None;
    let map_npy = args.out.join("map.npy");
    let map_ply = args.out.join("map.ply");
    let mut final_map_written = false;
    let observe = |view: &StepView<'_>| {
        if let Some(r) = recorder.as_mut() {
            if let Err(e) = r.step(view) {
                observe_error.get_or_insert(e);
            }
        }
        if args.figures {
            if let Some(s) = SliceSnapshot::capture(view) {
                snapshots.push(s);
            }
        }
        if view.finished {
            let map = view.planner.map();
            let written =
                figures::write_labels(map, &map_npy).and_then(|()| figures::write_ply(map, &map_ply));
            match written {
                Ok(()) => final_map_written = true,
                Err(e) => {
                    observe_error.get_or_insert(e);
                }
            }
        }
    };
    let report = if args.core == "qemu" {
        let pil = harmonic_sim::pil::PilConfig {
            firmware: args.firmware.clone(),
            qemu: args.qemu.clone(),
            out: args.out.clone(),
        };
        harmonic_sim::pil::run(&scenario, &cfg, &pil, on_step)
    } else {
        sim::run_observed(&scenario, &cfg, on_step, observe)
    }
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    if let Some(e) = observe_error {
        return Err(e);
    }
    if let Some(r) = recorder {
        let n = r.finish()?;
        if let Some(dir) = &args.record {
            println!("recorded {n} frames: {}", dir.display());
        }
    }
    if final_map_written {
        println!(
            "map: {} (labels), {} (occupied voxel centres)",
            map_npy.display(),
            map_ply.display()
        );
    }
    if args.figures {
        write_run_figures(&report, &snapshots, args.figure_step, &args.out)?;
    }

    let path = args.out.join("report.json");
    let json = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
    std::fs::write(&path, json).map_err(|e| format!("{}: {e}", path.display()))?;
    print_summary(&report);
    println!("report: {}", path.display());
    Ok(())
}

fn fault_campaign(args: &FaultsArgs) -> Result<(), String> {
    use harmonic_sim::faults;
    let scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    let mut cfg = SimConfig {
        max_scans: args.max_scans,
        seed: args.seed,
        ..SimConfig::default()
    };
    cfg.explorer.vehicle_radius = args.vehicle_radius;
    let cells: Vec<_> = if args.drift_rates.is_empty() {
        faults::default_matrix()
            .into_iter()
            .filter(|c| args.cells.is_empty() || args.cells.iter().any(|f| c.name.contains(f.as_str())))
            .collect()
    } else {
        args.drift_rates.iter().map(|&r| faults::drift_cell(r)).collect()
    };
    if cells.is_empty() {
        return Err(format!("--cells {}: no cell matches", args.cells.join(",")));
    }
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;
    let total = cells.len();
    let mut done = 0;
    let results = faults::run(&scenario, &cfg, cells, |r| {
        done += 1;
        eprintln!(
            "[{done}/{total}] {}: {}, {} collisions, {}/{} frames integrated",
            r.cell.name, r.termination, r.collisions, r.frames_integrated, r.frames_sent
        );
    });
    let table = faults::table(&results);
    print!("{table}");
    let json = serde_json::to_string_pretty(&results).map_err(|e| e.to_string())?;
    for (name, text) in [("faults.json", json), ("faults.md", table)] {
        let path = args.out.join(name);
        std::fs::write(&path, text).map_err(|e| format!("{}: {e}", path.display()))?;
    }
    let collisions: u32 = results.iter().map(|r| r.collisions).sum();
    if collisions > 0 {
        return Err(format!("{collisions} collisions in the fault matrix"));
    }
    Ok(())
}

/// RAM budget of the reference board (memory.x).
const RAM_BUDGET: u64 = 1024 * 1024;
/// Instruction budget of one planning cycle (10 Hz at 480 MHz).
const PLAN_BUDGET: u64 = 48_000_000;

fn fw_budget(args: &FwBudgetArgs) -> Result<(), String> {
    use harmonic_sim::pil;
    if args.stereo {
        return fw_stereo_budget(args);
    }
    let elf = match &args.firmware {
        Some(p) => p.clone(),
        None => pil::build_firmware(None).map_err(|e| e.to_string())?,
    };
    let size = pil::image_size(&elf)?;
    let kib = |b: u64| b as f64 / 1024.0;
    println!("firmware {}", elf.display());
    println!("| memory | bytes | KiB |");
    println!("|---|---|---|");
    println!(
        "| flash (.vector_table + .text + .rodata + .data) | {} | {:.1} |",
        size.flash,
        kib(size.flash)
    );
    println!("| .data | {} | {:.1} |", size.data, kib(size.data));
    println!("| .bss + .uninit | {} | {:.1} |", size.bss, kib(size.bss));
    println!(
        "| stack reserve | {} | {:.1} |",
        size.stack_reserve,
        kib(size.stack_reserve)
    );
    println!(
        "| **RAM (.data + .bss + stack reserve)** | **{}** | **{:.1}** of {:.0} ({:.1} % used) |",
        size.ram,
        kib(size.ram),
        kib(RAM_BUDGET),
        size.ram as f64 * 100.0 / RAM_BUDGET as f64
    );
    if size.ram > RAM_BUDGET {
        return Err(format!(
            "the image needs {} bytes of RAM, more than the {RAM_BUDGET} budget",
            size.ram
        ));
    }
    if args.sizes_only {
        return Ok(());
    }
    let scenario = Scenario::by_name_or_path(&args.scenario).map_err(|e| e.to_string())?;
    let cfg = SimConfig::default();
    let pil_cfg = pil::PilConfig {
        firmware: Some(elf),
        qemu: args.qemu.clone(),
        out: args.out.clone(),
    };
    eprintln!(
        "exploring {} with the firmware under QEMU (-icount shift=0) ...",
        args.scenario
    );
    let report = pil::run(&scenario, &cfg, &pil_cfg, |s| {
        if s.step.is_multiple_of(10) {
            eprintln!("  scan {}: {}", s.step, s.outcome);
        }
    })
    .map_err(|e| e.to_string())?;
    let path = args.out.join("report.json");
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?,
    )
    .map_err(|e| format!("{}: {e}", path.display()))?;
    let Some(p) = &report.pil else {
        return Err("no processor-in-the-loop data in the report".into());
    };
    match pil::stack_high_water(&args.out) {
        Some(deepest) => {
            println!(
                "stack high-water (stack painting, the firmware's log): {deepest} bytes of the {} reserved",
                size.stack_reserve
            );
            if deepest > size.stack_reserve {
                eprintln!(
                    "warning: the firmware's stack went {} bytes deeper than memory.x reserves for it",
                    deepest - size.stack_reserve
                );
            }
        }
        None => println!("stack high-water: not in the firmware's log (install defmt-print to decode it)"),
    }
    // Full replans (outcome "goal") solved; the first is the cold solve.
    let full: Vec<(usize, [u64; 4])> = report
        .steps
        .iter()
        .zip(&p.steps)
        .filter(|(s, _)| s.outcome == "goal")
        .map(|(s, i)| (s.unknowns as usize, *i))
        .collect();
    let mean = |v: &[u64]| {
        if v.is_empty() {
            0.0
        } else {
            v.iter().sum::<u64>() as f64 / v.len() as f64
        }
    };
    let max = |v: &[u64]| v.iter().copied().max().unwrap_or(0);
    let m = |x: f64| x / 1e6;
    let integrate: Vec<u64> = p.steps.iter().map(|s| s[0]).collect();
    let warm: Vec<u64> = full.iter().skip(1).map(|(_, i)| i[2]).collect();
    let domain: Vec<u64> = full.iter().map(|(_, i)| i[1]).collect();
    let streamline: Vec<u64> = full.iter().map(|(_, i)| i[3]).collect();
    let cycle: Vec<u64> = full.iter().map(|(_, i)| i[1] + i[2] + i[3]).collect();
    let (cold_unknowns, cold) = full.first().map(|(u, i)| (*u, i[2])).unwrap_or((0, 0));
    let largest = full.iter().map(|(u, _)| *u).max().unwrap_or(0);
    let cold_solves: Option<Vec<u64>> = match &args.cold_firmware {
        Some(elf) => {
            eprintln!("again with the cold-start image ...");
            let cold_cfg = pil::PilConfig {
                firmware: Some(elf.clone()),
                qemu: args.qemu.clone(),
                out: args.out.join("cold"),
            };
            let cold = pil::run(&scenario, &cfg, &cold_cfg, |_| {}).map_err(|e| e.to_string())?;
            let steps = cold.pil.map(|p| p.steps).unwrap_or_default();
            Some(
                cold.steps
                    .iter()
                    .zip(&steps)
                    .filter(|(s, _)| s.outcome == "goal")
                    .map(|(_, i)| i[2])
                    .collect(),
            )
        }
        None => None,
    };
    println!();
    println!(
        "{}: {} scans, {} full replans, termination {}, coverage {:.2} %; grid 64x64x32, domain up to {} unknowns",
        report.scenario,
        report.scans,
        full.len(),
        report.termination,
        report.coverage_free * 100.0,
        largest
    );
    println!("| phase (instructions, millions) | mean | max |");
    println!("|---|---|---|");
    println!(
        "| integrate one 100x100 frame | {:.1} | {:.1} |",
        m(mean(&integrate)),
        m(max(&integrate) as f64)
    );
    println!(
        "| domain (boundary conditions) | {:.1} | {:.1} |",
        m(mean(&domain)),
        m(max(&domain) as f64)
    );
    match &cold_solves {
        Some(c) => println!(
            "| cold solve (every replan from psi = 0, cold-start image) | {:.1} | {:.1} |",
            m(mean(c)),
            m(max(c) as f64)
        ),
        None => println!(
            "| cold solve (first plan, {cold_unknowns} unknowns; --cold-firmware for all) | {:.1} | |",
            m(cold as f64)
        ),
    }
    println!(
        "| warm re-solve | {:.1} | {:.1} |",
        m(mean(&warm)),
        m(max(&warm) as f64)
    );
    println!(
        "| streamline + goal | {:.2} | {:.2} |",
        m(mean(&streamline)),
        m(max(&streamline) as f64)
    );
    println!(
        "| **full planning cycle** (domain + solve + streamline) | **{:.1}** | **{:.1}** |",
        m(mean(&cycle)),
        m(max(&cycle) as f64)
    );
    println!(
        "target for a full planning cycle: {:.0} M instructions; reached: mean {:.1} M ({:.1}x), max {:.1} M",
        m(PLAN_BUDGET as f64),
        m(mean(&cycle)),
        mean(&cycle) / PLAN_BUDGET as f64,
        m(max(&cycle) as f64)
    );
    println!("report: {}", path.display());
    Ok(())
}

/// `fw-budget --stereo`: the matcher's instructions per frame on the emulated Cortex-M4F.
fn fw_stereo_budget(args: &FwBudgetArgs) -> Result<(), String> {
    use harmonic_sim::pil;
    let elf = match &args.firmware {
        Some(p) => p.clone(),
        None => pil::build_firmware_example("stereo_bench", None).map_err(|e| e.to_string())?,
    };
    let size = pil::image_size(&elf)?;
    println!("stereo_bench {}", elf.display());
    println!(
        "RAM (.data + .bss + stack reserve) {} bytes ({:.1} KiB), flash {:.1} KiB",
        size.ram,
        size.ram as f64 / 1024.0,
        size.flash as f64 / 1024.0
    );
    let out = pil::run_semihosted(&args.qemu, &elf, std::time::Duration::from_secs(600))
        .map_err(|e| e.to_string())?;
    println!("| frame | window | prefilter | matcher scratch (bytes) | instructions (millions) | per pixel-disparity | disparity to depth (millions) | density % | bad-1.0 % |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut rows = 0;
    for line in out.lines().filter(|l| l.starts_with("stereo ")) {
        let field = |key: &str| {
            line.split_whitespace()
                .find_map(|kv| kv.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
                .unwrap_or("?")
        };
        let num = |key: &str| field(key).parse::<f64>().unwrap_or(f64::NAN);
        let work = num("width") * num("height") * num("ndisp");
        println!(
            "| {}x{}x{} | {} | {} | {} | {:.1} | {:.1} | {:.2} | {:.1} | {:.2} |",
            field("width"),
            field("height"),
            field("ndisp"),
            field("window"),
            field("prefilter"),
            field("scratch_bytes"),
            num("match_instructions") / 1e6,
            num("match_instructions") / work,
            num("depth_instructions") / 1e6,
            100.0 * num("valid") / num("known"),
            100.0 * num("bad1") / num("valid")
        );
        rows += 1;
    }
    if rows == 0 {
        return Err(format!("stereo_bench printed no results:\n{out}"));
    }
    println!("instructions from the board timer under QEMU -icount shift=0 (1 tick = 40 instructions); density and bad-1.0 against the synthetic pair's ground truth (pixels visible to both cameras)");
    Ok(())
}

/// The slice (at `--figure-step`, else the full plan a third of the way through the run), the
/// top view and the run's coverage curve.
fn write_run_figures(
    report: &Report,
    snapshots: &[SliceSnapshot],
    step: Option<u32>,
    out: &std::path::Path,
) -> Result<(), String> {
    let target = step.unwrap_or(report.steps_taken / 3);
    let snap = snapshots
        .iter()
        .find(|s| s.step >= target)
        .or_else(|| snapshots.last());
    let mut written = Vec::new();
    if let Some(snap) = snap {
        let p = out.join("slice.png");
        figures::slice_figure(snap, &report.scenario, &p)?;
        written.push(p);
    }
    let p = out.join("top_view.png");
    // The top view draws the map from map.npy, exactly as exported.
    let grid = npy::read_u8_file(out.join("map.npy")).map_err(|e| format!("map.npy: {e}"))?;
    figures::top_view_labels(
        &grid,
        report.grid_origin,
        report.resolution,
        &report.trajectory,
        &format!(
            "{}, {}: {:.1} m flown, {:.1} % free coverage",
            report.scenario,
            report.planner,
            report.path_length_m,
            100.0 * report.coverage_free
        ),
        &p,
    )?;
    written.push(p);
    let curve = batch::Curve {
        scenario: report.scenario.clone(),
        planner: report.planner.clone(),
        seed: 0,
        points: report
            .steps
            .iter()
            .map(|s| (s.path_length_m, s.coverage_free))
            .collect(),
    };
    let p = out.join("coverage.png");
    figures::coverage_curves(&[curve], &report.scenario, &p)?;
    written.push(p);
    for p in written {
        println!("figure: {}", p.display());
    }
    Ok(())
}

fn bench_solve(args: &BenchSolveArgs) {
    let screening = if args.field == "screened" {
        let k = harmonic_core::field::ScreenedParams::default().kappa_voxel(0.1);
        k * k
    } else {
        0.0
    };
    println!("| grid | unknowns | frontier | solver | start | iterations | residual | error estimate | ms | cell updates |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut mg_cold_ms = Vec::new();
    for dims in &args.sizes {
        let mut solvers = vec![
            BenchSolver::Multigrid(Method::Pcg),
            BenchSolver::Multigrid(Method::VCycle),
        ];
        if dims.len() <= args.gs_max_voxels {
            solvers.push(BenchSolver::GaussSeidel);
        }
        let mut rows = Vec::new();
        for solver in solvers {
            eprintln!(
                "measuring {} on {}x{}x{} ...",
                solver_label(solver),
                dims.nx(),
                dims.ny(),
                dims.nz()
            );
            for row in bench::measure(*dims, solver, args.tol, args.repeat, screening) {
                println!(
                    "| {} | {} | {} | {} | {} | {} | {:.1e} | {} | {:.2} | {} |",
                    row.grid,
                    row.unknowns,
                    row.frontier,
                    row.solver,
                    row.start,
                    row.iterations,
                    row.residual,
                    row.error_estimate.map_or("–".to_string(), |e| format!("{e:.1e}")),
                    row.ms,
                    row.cell_updates
                );
                rows.push(row);
            }
        }
        let find = |solver: &str, start: &str| rows.iter().find(|r| r.solver == solver && r.start == start);
        if let (Some(mg), Some(gs)) = (find("mg (pcg)", "cold"), find("gs", "cold")) {
            println!(
                "\n{}: Gauss-Seidel / MGPCG, cold: time {:.0}×, cell updates {:.0}×\n",
                mg.grid,
                gs.ms / mg.ms,
                gs.cell_updates as f64 / mg.cell_updates as f64
            );
        }
        if let Some(mg) = find("mg (pcg)", "cold") {
            mg_cold_ms.push((dims.len(), mg.ms));
        }
    }
    for pair in mg_cold_ms.windows(2) {
        println!(
            "growth: {:.1}× the voxels took {:.1}× the MGPCG cold-solve time",
            pair[1].0 as f64 / pair[0].0 as f64,
            pair[1].1 / pair[0].1
        );
    }
}

fn solver_label(s: BenchSolver) -> &'static str {
    match s {
        BenchSolver::Multigrid(Method::VCycle) => "multigrid V-cycles",
        BenchSolver::Multigrid(_) => "MGPCG",
        BenchSolver::GaussSeidel => "Gauss-Seidel",
    }
}

fn print_summary(r: &Report) {
    let rows: [(&str, String); 15] = [
        ("scenario", r.scenario.clone()),
        ("planner", r.planner.clone()),
        ("termination", r.termination.clone()),
        ("coverage (free)", format!("{:.2} %", r.coverage_free * 100.0)),
        (
            "coverage (observed)",
            format!("{:.2} %", r.coverage_observed * 100.0),
        ),
        (
            "coverage (surface)",
            format!("{:.2} %", r.coverage_surface * 100.0),
        ),
        ("path length", format!("{:.1} m", r.path_length_m)),
        ("scans", r.scans.to_string()),
        ("collisions", r.collisions.to_string()),
        ("integration ops", r.integration_ops.to_string()),
        ("planning ops", r.planning_ops.to_string()),
        (
            "integrate / step",
            format!("{:.2} ms", r.timing.integrate.mean_ms),
        ),
        (
            "solve / step",
            format!(
                "{:.2} ms (max {:.1})",
                r.timing.solve.mean_ms, r.timing.solve.max_ms
            ),
        ),
        (
            "domain + streamline",
            format!("{:.2} ms", r.timing.domain.mean_ms + r.timing.streamline.mean_ms),
        ),
        ("wall time", format!("{:.1} s", r.wall_time_s)),
    ];
    let mut rows = rows.to_vec();
    if let Some(n) = r.unreachable_frontier_voxels {
        rows.insert(
            3,
            (
                "left unreachable",
                format!(
                    "{n} frontier voxels seen but out of reach (too narrow for the vehicle, behind a gap); {} unknown voxels sealed as unobservable",
                    r.sealed_voxels
                ),
            ),
        );
    }
    if let Some(a) = &r.map_accuracy {
        rows.push((
            "map accuracy",
            format!(
                "{:.2} % of all voxels, {:.2} % of observed ones match the noise-free map ({} false occupied, {} false free); {} reachable free voxels held occupied",
                100.0 * a.all_voxels,
                100.0 * a.observed_voxels,
                a.false_occupied,
                a.false_free,
                r.free_marked_occupied
            ),
        ));
    }
    if let Some([e, y]) = r.final_drift {
        rows.push(("final drift", format!("{e:.2} m, {:.1}°", y.to_degrees())));
    }
    if let Some(s) = &r.stereo {
        rows.push((
            "stereo depth",
            format!(
                "{} pairs of {}x{} px, baseline {} m, {} disparities, window {}: {:.1} % of pixels matched, {:.1} % of depth pixels valid; render {:.1} ms, match {:.1} ms per pair",
                s.frames,
                s.render_size[0],
                s.render_size[1],
                s.baseline_m,
                s.num_disparities,
                s.window,
                100.0 * s.mean_match_density,
                100.0 * s.mean_depth_density,
                s.mean_render_ms,
                s.mean_match_ms
            ),
        ));
    }
    let l = &r.link;
    rows.push((
        "depth link",
        format!(
            "{} at {} baud: {} frames sent, {} integrated, {} lost; {:.0} ms per frame (max {:.0})",
            l.transport,
            l.baud,
            l.depth_frames_sent,
            l.depth_frames_integrated,
            l.depth_frames_lost,
            l.transfer.mean_ms,
            l.transfer.max_ms
        ),
    ));
    let c = &l.receiver;
    rows.push((
        "link errors",
        format!(
            "crc {}, cobs {}, oversize {}, malformed {}, seq gaps {}, out-of-order {}, missing chunks {}, no pose {}",
            c.crc_errors,
            c.cobs_errors,
            c.oversize,
            c.malformed,
            c.sequence_gaps,
            c.out_of_order_chunks,
            c.missing_chunks,
            l.frames_without_pose
        ),
    ));
    if l.resend_requests_sent > 0 || l.partial_frames_integrated > 0 {
        rows.push((
            "link recovery",
            format!(
                "{} partial frames integrated ({} rows missing); {} resend requests (up to {} per frame), {} chunks resent ({:.0} kB); {:.1} rows per chunk (BER estimate {:.1e})",
                l.partial_frames_integrated,
                c.rows_missing,
                l.resend_requests_sent,
                l.arq_rounds,
                l.chunks_resent,
                l.bytes_resent as f64 / 1e3,
                l.rows_per_chunk_mean,
                l.ber_estimate
            ),
        ));
    }
    if let Some(f) = &l.injected {
        rows.push((
            "link faults",
            format!(
                "{} frames dropped, {} duplicated, {} reordered; {} bits flipped, {} bytes dropped, {} bursts",
                f.frames_dropped, f.frames_duplicated, f.frames_reordered, f.bits_flipped, f.bytes_dropped, f.bursts
            ),
        ));
    }
    if let Some(m) = &r.mavlink {
        let t = &m.traffic;
        rows.push((
            "mavlink",
            format!(
                "{}: {} messages out, {} in; setpoints {:.1} Hz, max gap {} ms",
                m.endpoint, t.messages_sent, t.messages_received, t.setpoint_rate_hz, t.max_setpoint_gap_ms
            ),
        ));
        rows.push((
            "mavlink out",
            format!(
                "{} setpoints, {} heartbeats, {} statustexts",
                m.bridge.setpoints_sent, m.bridge.heartbeats_sent, m.bridge.status_texts_sent,
            ),
        ));
        rows.push((
            "mavlink in",
            format!(
                "{} local positions, {} attitudes, {} odometries; {} rejected, {} stale events",
                m.bridge.local_positions_received,
                m.bridge.attitudes_received,
                m.bridge.odometries_received,
                m.bridge.rejected(),
                m.bridge.stale_events
            ),
        ));
        if let Some(t) = &m.tlog {
            rows.push(("tlog", format!("{} ({} records)", t.path, t.records)));
        }
    }
    println!();
    for (k, v) in rows {
        println!("  {k:<20} {v}");
    }
}
