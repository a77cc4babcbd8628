//! `harmonic-sim fw-budget`: the firmware's RAM, flash and instructions per phase under QEMU,
//! and with `--stereo` the matcher's instructions per frame.

use std::path::PathBuf;

use harmonic_sim::run::sim::SimConfig;
use harmonic_sim::world::scenario::Scenario;

/// The flags of `fw-budget`.
#[derive(clap::Args)]
pub struct FwBudgetArgs {
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

/// RAM budget of the reference board (memory.x).
const RAM_BUDGET: u64 = 1024 * 1024;
/// Instruction budget of one planning cycle (10 Hz at 480 MHz).
const PLAN_BUDGET: u64 = 48_000_000;

/// Run `fw-budget`: the image sizes, then (unless `--sizes-only`) the instructions per phase of
/// a processor-in-the-loop run; with `--stereo`, the matcher's budget instead.
pub fn run(args: &FwBudgetArgs) -> Result<(), String> {
    use harmonic_sim::run::pil;
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
        intruder: Vec::new(),
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
                intruder: Vec::new(),
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
        "{}: {} scans, {} full replans, termination {}, coverage {:.2} %; grid {}x{}x{} ({} voxels of the firmware's {}), domain up to {} unknowns",
        report.scenario,
        report.scans,
        full.len(),
        report.termination,
        report.coverage_free * 100.0,
        report.grid[0],
        report.grid[1],
        report.grid[2],
        report.grid.iter().product::<usize>(),
        harmonic_fw::app::CAPACITY,
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
    use harmonic_sim::run::pil;
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
    let lines = pil::stereo_bench_lines(&out)?;
    println!("| frame | window | prefilter | matcher scratch (bytes) | instructions (millions) | per pixel-disparity | portable code (millions) | disparity to depth (millions) | density % | bad-1.0 % |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for line in lines {
        let (field, num) = (|k| line.field(k), |k| line.num(k));
        let work = num("width") * num("height") * num("ndisp");
        println!(
            "| {}x{}x{} | {} | {} | {} | {:.1} | {:.1} | {:.1} | {:.2} | {:.1} | {:.2} |",
            field("width"),
            field("height"),
            field("ndisp"),
            field("window"),
            field("prefilter"),
            field("scratch_bytes"),
            num("match_instructions") / 1e6,
            num("match_instructions") / work,
            num("portable_instructions") / 1e6,
            num("depth_instructions") / 1e6,
            100.0 * num("valid") / num("known"),
            100.0 * num("bad1") / num("valid")
        );
    }
    println!("instructions from the board timer under QEMU -icount shift=0 (1 tick = 40 instructions); the DSP path's and the portable code's disparities identical in every configuration; density and bad-1.0 against the synthetic pair's ground truth (pixels visible to both cameras)");
    Ok(())
}
