//! `harmonic-sim stereo`, `stereo-render` and `bench-stereo`: the core's block matcher on PNG
//! pairs and on pairs rendered from scenarios, with the matcher flags the three share.

use std::path::PathBuf;

use harmonic_sim::world::scenario::Scenario;

use super::parse::{parse_positive, parse_prefilter};

/// The matcher's settings on the command line.
#[derive(clap::Args, Clone)]
pub struct MatcherArgs {
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
    /// Minimum mean horizontal gradient over the centre window, grey levels (0: off, the
    /// default: the uniqueness test rejects flat regions).
    #[arg(long, default_value_t = 0)]
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
    /// The matcher's parameters for a `width` x `height` pair with these flags.
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

/// The flags of `stereo`.
#[derive(clap::Args)]
#[command(
    after_help = "Disparity files (--out, --gt) hold float32 pixels: PFM (.pfm, Middlebury's \
format, little-endian, rows bottom to top) or NumPy (.npy, shape (H, W)). Pixels without a valid \
match are +inf in both formats (Middlebury's convention for unknown disparity; np.isfinite \
selects the valid ones). Ground-truth pixels that are not finite are not evaluated."
)]
pub struct StereoArgs {
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
    /// Match in this many horizontal bands at once, one per thread (0: one per core). The
    /// result is the same for any number.
    #[arg(long, default_value_t = 0)]
    threads: usize,
    #[command(flatten)]
    matcher: MatcherArgs,
}

/// The flags of `stereo-render`.
#[derive(clap::Args)]
pub struct StereoRenderArgs {
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

/// The flags of `bench-stereo`.
#[derive(clap::Args)]
pub struct BenchStereoArgs {
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

/// Run `stereo`: match the pair, write the disparity, print the statistics (and with `--gt`
/// the bad-pixel rates).
pub fn run_match(args: &StereoArgs) -> Result<(), String> {
    use harmonic_sim::sensors::stereo as st;
    let (w, h, left) = st::read_png_gray(&args.left)?;
    let (wr, hr, right) = st::read_png_gray(&args.right)?;
    if (w, h) != (wr, hr) {
        return Err(format!("left is {w}x{h}, right is {wr}x{hr}"));
    }
    let params = args.matcher.params(w, h);
    let bands = if args.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.threads
    };
    // One match, timed as it is (fresh memory and the threads' start included): what a
    // user's process pays.
    let t0 = std::time::Instant::now();
    let (disparity, stats) = st::match_pair_bands(params, &left, &right, bands)?;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let disparity = st::disparity_to_f32(&disparity);
    st::write_disparity(&args.out, w, h, &disparity)?;
    let n = f64::from(w) * f64::from(h);
    println!(
        "{w}x{h}, {} disparities, window {}: {:.1} ms on {bands} thread(s) ({:.2} ns per pixel-disparity); {:.1} % of pixels matched",
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

/// Run `stereo-render`: render the pair with its ground truth into the output directory.
pub fn run_render(args: &StereoRenderArgs) -> Result<(), String> {
    use harmonic_sim::sensors::stereo as st;
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
    let k =
        rig.render_intrinsics(&harmonic_sim::sensors::camera::DepthCamera::default_thesis().intrinsics)?;
    let pose = harmonic_sim::sensors::camera::camera_pose(&scenario.start_position, scenario.start_yaw);
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

/// Run `bench-stereo`: render, match and score the pairs of every scenario and print the table.
pub fn run_bench(args: &BenchStereoArgs) -> Result<(), String> {
    use harmonic_sim::sensors::stereo as st;
    use rand::SeedableRng;
    let camera = harmonic_sim::sensors::camera::DepthCamera::default_thesis();
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
            let pose =
                harmonic_sim::sensors::camera::camera_pose(&scenario.start_position, scenario.start_yaw);
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
