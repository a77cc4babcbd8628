//! `harmonic-sim replay`: integrate a recorded depth sequence and write the map (the replay
//! itself is `harmonic_sim::run::record`).

use std::path::PathBuf;

use harmonic_sim::run::record;
use harmonic_sim::tools::figures;

use super::parse::parse_positive;

/// The flags of `replay`.
#[derive(clap::Args)]
pub struct ReplayArgs {
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

/// Run `replay`: integrate the sequence, write map.npy and map.ply, print the summary as JSON.
pub fn run(args: &ReplayArgs) -> Result<(), String> {
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
