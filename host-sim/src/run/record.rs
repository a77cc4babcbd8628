//! Recorded runs and replay, in the TUM RGB-D layout.
//!
//! `explore --record DIR` writes
//!
//! ```text
//! DIR/depth/<timestamp>.png   every integrated depth frame: 16-bit grey PNG, millimetres, 0 = no return
//! DIR/depth.txt               "timestamp filename" per frame (TUM RGB-D)
//! DIR/groundtruth.txt         "timestamp tx ty tz qx qy qz qw": camera → map pose, camera frame
//!                             x right, y down, z forward (TUM RGB-D); the pose each frame was
//!                             integrated with (the truth unless drift is simulated)
//! DIR/intrinsics.txt          "fx fy cx cy width height"
//! DIR/map.json                the map's grid, log-odds, range limits and vehicle radius
//! DIR/vehicle.txt             "timestamp x y z": where the planner planned (the core marks the
//!                             vehicle's body free there)
//! ```
//!
//! Timestamps are simulated seconds. `harmonic-sim replay DIR` integrates the sequence through
//! the core ([`harmonic_core::integrate`]) into a fresh map — ours exactly as the explorer did
//! (frames in order, the body marked after each step's frames), so a noise-free recording
//! reproduces the explorer's final map voxel for voxel — or any TUM RGB-D–style sequence given
//! its intrinsics, a depth scale (TUM: 5000 per metre) and a grid.

use std::collections::BTreeMap;
use std::fs;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use harmonic_core::camera::{DepthFrame, Intrinsics};
use harmonic_core::domain::InflationStencil;
use harmonic_core::integrate::{integrate, IntegrationParams};
use harmonic_core::map::{Dims, LogOddsParams, MapGeometry, VoxelMap};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use crate::run::sim::StepView;

/// The map settings a recording was made with (`map.json`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapSettings {
    /// Grid origin (minimum corner), map frame, metres.
    pub origin: [f32; 3],
    /// Voxels along x, y, z.
    pub dims: [usize; 3],
    /// Voxel edge, metres.
    pub resolution: f32,
    /// Log-odds hit, miss, min, max.
    pub log_odds: [f32; 4],
    /// Integration range limits, metres.
    pub min_range: f32,
    /// See `min_range`.
    pub max_range: f32,
    /// Vehicle radius (the body marked free), metres; 0: no body marks.
    pub vehicle_radius: f32,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> String + '_ {
    move |e| format!("{}: {e}", path.display())
}

/// Writes a recording as a run goes (see the [module documentation](self)).
pub struct Recorder {
    dir: PathBuf,
    depth_txt: String,
    groundtruth_txt: String,
    vehicle_txt: String,
    intrinsics: Option<Intrinsics>,
    frames: usize,
}

impl Recorder {
    /// Creates `dir` (and `dir/depth`) and writes `map.json`.
    pub fn create(dir: &Path, settings: &MapSettings) -> Result<Self, String> {
        fs::create_dir_all(dir.join("depth")).map_err(io(dir))?;
        let json = serde_json::to_string_pretty(settings).map_err(|e| e.to_string())?;
        fs::write(dir.join("map.json"), json).map_err(io(dir))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            depth_txt: "# depth maps\n# 16-bit PNG, millimetres, 0 = no return\n# timestamp filename\n".into(),
            groundtruth_txt: "# camera trajectory (camera -> map; camera x right, y down, z forward)\n# timestamp tx ty tz qx qy qz qw\n"
                .into(),
            vehicle_txt: "# where the planner planned (the vehicle body is marked free there)\n# timestamp x y z\n".into(),
            intrinsics: None,
            frames: 0,
        })
    }

    /// Records the frames and the plan position of one step.
    pub fn step(&mut self, view: &StepView<'_>) -> Result<(), String> {
        let mut last_t = None;
        for f in view.frames {
            let t = format!("{:.6}", f.time_s + 1e-6 * self.frames as f64);
            let name = format!("depth/{t}.png");
            write_png16(
                &self.dir.join(&name),
                &f.depth_mm,
                f.intrinsics.width(),
                f.intrinsics.height(),
            )?;
            self.depth_txt.push_str(&format!("{t} {name}\n"));
            let p = f.camera_pose.translation.vector;
            let q = f.camera_pose.rotation.quaternion();
            self.groundtruth_txt.push_str(&format!(
                "{t} {:?} {:?} {:?} {:?} {:?} {:?} {:?}\n",
                p.x, p.y, p.z, q.i, q.j, q.k, q.w
            ));
            self.intrinsics = Some(f.intrinsics);
            self.frames += 1;
            last_t = Some(t);
        }
        if let (Some(p), Some(t)) = (view.planned_at, last_t) {
            self.vehicle_txt
                .push_str(&format!("{t} {:?} {:?} {:?}\n", p.x, p.y, p.z));
        }
        Ok(())
    }

    /// Writes the text files. Returns the number of frames recorded.
    pub fn finish(self) -> Result<usize, String> {
        let d = &self.dir;
        fs::write(d.join("depth.txt"), &self.depth_txt).map_err(io(d))?;
        fs::write(d.join("groundtruth.txt"), &self.groundtruth_txt).map_err(io(d))?;
        fs::write(d.join("vehicle.txt"), &self.vehicle_txt).map_err(io(d))?;
        if let Some(k) = self.intrinsics {
            fs::write(
                d.join("intrinsics.txt"),
                format!(
                    "# fx fy cx cy width height (pixels)\n{:?} {:?} {:?} {:?} {} {}\n",
                    k.fx(),
                    k.fy(),
                    k.cx(),
                    k.cy(),
                    k.width(),
                    k.height()
                ),
            )
            .map_err(io(d))?;
        }
        Ok(self.frames)
    }
}

/// Writes a 16-bit greyscale PNG.
pub fn write_png16(path: &Path, values: &[u16], width: u16, height: u16) -> Result<(), String> {
    let file = fs::File::create(path).map_err(io(path))?;
    let mut enc = png::Encoder::new(BufWriter::new(file), u32::from(width), u32::from(height));
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    let mut w = enc
        .write_header()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
    w.write_image_data(&bytes)
        .map_err(|e| format!("{}: {e}", path.display()))
}

/// Reads a 16-bit greyscale PNG: `(values, width, height)`.
pub fn read_png16(path: &Path) -> Result<(Vec<u16>, u16, u16), String> {
    let file = fs::File::open(path).map_err(io(path))?;
    let dec = png::Decoder::new(std::io::BufReader::new(file));
    let mut reader = dec.read_info().map_err(|e| format!("{}: {e}", path.display()))?;
    let info = reader.info();
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(format!(
            "{}: expected a 16-bit greyscale PNG, found {:?} {:?}",
            path.display(),
            info.color_type,
            info.bit_depth
        ));
    }
    let (w, h) = (info.width, info.height);
    let mut buf = vec![0u8; reader.output_buffer_size()];
    reader
        .next_frame(&mut buf)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let values = buf
        .chunks_exact(2)
        .take((w * h) as usize)
        .map(|b| u16::from_be_bytes([b[0], b[1]]))
        .collect();
    let (w, h) = (u16::try_from(w), u16::try_from(h));
    match (w, h) {
        (Ok(w), Ok(h)) => Ok((values, w, h)),
        _ => Err(format!("{}: image too large", path.display())),
    }
}

/// How to replay a sequence.
#[derive(Debug, Clone)]
pub struct ReplayConfig {
    /// The sequence directory.
    pub dir: PathBuf,
    /// Intrinsics; default: `DIR/intrinsics.txt`.
    pub intrinsics: Option<Intrinsics>,
    /// Map settings; default: `DIR/map.json`, else a grid around the trajectory.
    pub map: Option<MapSettings>,
    /// Depth units per metre in the PNGs (ours: 1000; TUM RGB-D: 5000).
    pub depth_scale: f32,
    /// Largest timestamp difference for associating a depth frame with a pose, s.
    pub max_time_difference: f64,
}

/// What a replay produced.
#[derive(Debug, Clone, Serialize)]
pub struct ReplaySummary {
    /// Frames integrated.
    pub frames: usize,
    /// Depth frames with no pose close enough in time (skipped).
    pub frames_without_pose: usize,
    /// Body marks applied.
    pub body_marks: usize,
    /// Voxel updates.
    pub voxel_updates: u64,
    /// Grid size.
    pub dims: [usize; 3],
    /// Free, occupied and unknown voxels at the end.
    pub free: u32,
    /// See `free`.
    pub occupied: u32,
    /// See `free`.
    pub unknown: u32,
}

/// `timestamp rest...` lines of a TUM-style text file (comments skipped).
fn timed_lines(path: &Path) -> Result<Vec<(f64, String, Vec<String>)>, String> {
    let text = fs::read_to_string(path).map_err(io(path))?;
    let mut out = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut parts = line.split_whitespace();
        let t_text = parts.next().unwrap_or("").to_string();
        let t: f64 = t_text
            .parse()
            .map_err(|_| format!("{}:{}: bad timestamp `{t_text}`", path.display(), k + 1))?;
        out.push((t, t_text, parts.map(str::to_string).collect()));
    }
    Ok(out)
}

fn parse_f32s(fields: &[String], n: usize, path: &Path, what: &str) -> Result<Vec<f32>, String> {
    if fields.len() < n {
        return Err(format!("{}: {what}: expected {n} numbers", path.display()));
    }
    fields[..n]
        .iter()
        .map(|f| {
            f.parse::<f32>()
                .map_err(|_| format!("{}: {what}: bad number `{f}`", path.display()))
        })
        .collect()
}

/// Reads `intrinsics.txt` ("fx fy cx cy width height").
pub fn read_intrinsics(path: &Path) -> Result<Intrinsics, String> {
    let text = fs::read_to_string(path).map_err(io(path))?;
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .ok_or_else(|| format!("{}: no intrinsics line", path.display()))?;
    let f: Vec<String> = line.split_whitespace().map(str::to_string).collect();
    parse_intrinsics(&f).map_err(|e| format!("{}: {e}", path.display()))
}

/// Intrinsics from `fx fy cx cy width height`.
pub fn parse_intrinsics(f: &[String]) -> Result<Intrinsics, String> {
    if f.len() != 6 {
        return Err("expected fx fy cx cy width height".into());
    }
    let n: Vec<f32> = f[..4]
        .iter()
        .map(|x| x.parse::<f32>().map_err(|_| format!("bad number `{x}`")))
        .collect::<Result<_, _>>()?;
    let w: u16 = f[4].parse().map_err(|_| format!("bad width `{}`", f[4]))?;
    let h: u16 = f[5].parse().map_err(|_| format!("bad height `{}`", f[5]))?;
    Intrinsics::new(n[0], n[1], n[2], n[3], w, h).map_err(|e| format!("invalid intrinsics: {e:?}"))
}

/// Replays a sequence into a fresh map; calls `done` with the map before it is dropped.
pub fn replay(
    cfg: &ReplayConfig,
    done: impl FnOnce(&VoxelMap<'_>) -> Result<(), String>,
) -> Result<ReplaySummary, String> {
    let dir = &cfg.dir;
    let intrinsics = match cfg.intrinsics {
        Some(k) => k,
        None => read_intrinsics(&dir.join("intrinsics.txt"))
            .map_err(|e| format!("{e} (give --intrinsics fx,fy,cx,cy,width,height)"))?,
    };
    let depth_path = dir.join("depth.txt");
    let gt_path = dir.join("groundtruth.txt");
    let depth = timed_lines(&depth_path)?;
    let poses: Vec<(f64, Isometry3<f32>)> = timed_lines(&gt_path)?
        .into_iter()
        .map(|(t, _, f)| {
            let v = parse_f32s(&f, 7, &gt_path, "pose")?;
            let q = Quaternion::new(v[6], v[3], v[4], v[5]);
            // A unit quaternion as written is used as is, so a replay is bit-exact.
            let r = if (q.norm() - 1.0).abs() < 1e-6 {
                UnitQuaternion::new_unchecked(q)
            } else {
                UnitQuaternion::new_normalize(q)
            };
            Ok((t, Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), r)))
        })
        .collect::<Result<_, String>>()?;
    if poses.is_empty() {
        return Err(format!("{}: no poses", gt_path.display()));
    }
    let settings = match cfg.map {
        Some(m) => m,
        None => match fs::read_to_string(dir.join("map.json")) {
            Ok(text) => {
                serde_json::from_str(&text).map_err(|e| format!("{}: {e}", dir.join("map.json").display()))?
            }
            Err(_) => grid_around(&poses),
        },
    };
    let vehicle: Vec<(f64, Point3<f32>)> = match fs::read_to_string(dir.join("vehicle.txt")) {
        Ok(_) => timed_lines(&dir.join("vehicle.txt"))?
            .into_iter()
            .map(|(t, _, f)| {
                let v = parse_f32s(&f, 3, &dir.join("vehicle.txt"), "position")?;
                Ok((t, Point3::new(v[0], v[1], v[2])))
            })
            .collect::<Result<_, String>>()?,
        Err(_) => Vec::new(),
    };

    let [nx, ny, nz] = settings.dims;
    let dims = Dims::new(nx, ny, nz).map_err(|e| format!("map dims {nx}x{ny}x{nz}: {e:?}"))?;
    let geometry = MapGeometry::new(dims, Point3::from(settings.origin), settings.resolution)
        .map_err(|e| format!("map: {e:?}"))?;
    let [hit, miss, min, max] = settings.log_odds;
    let (mut lo, mut st) = (
        vec![0i8; dims.len()],
        vec![0u32; harmonic_core::map::touched_words(&dims)],
    );
    let mut map = VoxelMap::new(geometry, LogOddsParams { hit, miss, min, max }, &mut lo, &mut st)
        .map_err(|e| format!("map: {e:?}"))?;
    let params = IntegrationParams {
        min_range: settings.min_range,
        max_range: settings.max_range,
        pixel_stride: 1,
        ..IntegrationParams::default()
    };
    let stencil = (settings.vehicle_radius > 0.0)
        .then(|| InflationStencil::new(settings.vehicle_radius, settings.resolution))
        .transpose()
        .map_err(|e| format!("vehicle radius: {e:?}"))?;

    // Events in time order: a step's frames, then its body mark.
    let mut events: BTreeMap<(i64, u8, usize), Event> = BTreeMap::new();
    let key = |t: f64| (t * 1e6).round() as i64;
    for (k, (t, _, f)) in depth.iter().enumerate() {
        let file = f
            .first()
            .ok_or_else(|| format!("{}: line without a file name", depth_path.display()))?;
        events.insert((key(*t), 0, k), Event::Frame(*t, dir.join(file)));
    }
    for (k, (t, p)) in vehicle.iter().enumerate() {
        events.insert((key(*t), 1, k), Event::Body(*p));
    }
    let mut summary = ReplaySummary {
        frames: 0,
        frames_without_pose: 0,
        body_marks: 0,
        voxel_updates: 0,
        dims: settings.dims,
        free: 0,
        occupied: 0,
        unknown: 0,
    };
    let mut mm = Vec::new();
    for event in events.values() {
        match event {
            Event::Frame(t, file) => {
                let k = poses.partition_point(|(pt, _)| pt < t);
                let nearest = [k.checked_sub(1), Some(k)]
                    .into_iter()
                    .flatten()
                    .filter_map(|i| poses.get(i))
                    .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()));
                let Some((pt, pose)) = nearest.filter(|(pt, _)| (pt - t).abs() <= cfg.max_time_difference)
                else {
                    summary.frames_without_pose += 1;
                    continue;
                };
                let _ = pt;
                let (values, w, h) = read_png16(file)?;
                if (w, h) != (intrinsics.width(), intrinsics.height()) {
                    return Err(format!(
                        "{}: {w}x{h} pixels, the intrinsics say {}x{}",
                        file.display(),
                        intrinsics.width(),
                        intrinsics.height()
                    ));
                }
                mm.clear();
                if (cfg.depth_scale - 1000.0).abs() < f32::EPSILON {
                    mm.extend_from_slice(&values);
                } else {
                    mm.extend(values.iter().map(|&v| {
                        let m = (f32::from(v) * 1000.0 / cfg.depth_scale).round();
                        if v == 0 {
                            0
                        } else {
                            m.clamp(1.0, f32::from(u16::MAX - 1)) as u16
                        }
                    }));
                }
                let frame =
                    DepthFrame::new(intrinsics, &mm).map_err(|e| format!("{}: {e:?}", file.display()))?;
                let stats = integrate(&mut map, &frame, pose, &params)
                    .map_err(|e| format!("{}: {e:?}", file.display()))?;
                summary.voxel_updates += u64::from(stats.voxel_updates);
                summary.frames += 1;
            }
            Event::Body(p) => {
                if let Some(stencil) = &stencil {
                    harmonic_core::domain::mark_body(&mut map, stencil, p);
                    summary.body_marks += 1;
                }
            }
        }
    }
    let counts = map.counts();
    summary.free = counts.free;
    summary.occupied = counts.occupied;
    summary.unknown = counts.unknown;
    done(&map)?;
    Ok(summary)
}

enum Event {
    Frame(f64, PathBuf),
    Body(Point3<f32>),
}

/// A 0.05 m grid (at most 256 voxels per axis) over the trajectory ± 4 m, for sequences without
/// `map.json`.
fn grid_around(poses: &[(f64, Isometry3<f32>)]) -> MapSettings {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for (_, p) in poses {
        for a in 0..3 {
            lo[a] = lo[a].min(p.translation.vector[a] - 4.0);
            hi[a] = hi[a].max(p.translation.vector[a] + 4.0);
        }
    }
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0f32, f32::max);
    let resolution = (extent / 256.0).max(0.05);
    let dims = [0, 1, 2].map(|a| (((hi[a] - lo[a]) / resolution).ceil() as usize).clamp(1, 256));
    let d = LogOddsParams::default();
    MapSettings {
        origin: lo,
        dims,
        resolution,
        log_odds: [d.hit, d.miss, d.min, d.max],
        min_range: 0.3,
        max_range: 4.0,
        vehicle_radius: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png16_round_trips() {
        let dir = std::env::temp_dir().join(format!("hs-png-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("d.png");
        let values: Vec<u16> = (0..12).map(|i| i * 5000 + 1).collect();
        write_png16(&path, &values, 4, 3).unwrap();
        assert_eq!(read_png16(&path).unwrap(), (values, 4, 3));
        let _ = fs::remove_dir_all(dir);
    }
}
