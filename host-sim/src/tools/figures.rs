//! PNG figures (plotters, bitmap backend, the DejaVu Sans font embedded — no system fonts
//! needed) and map exports.
//!
//! - [`slice_figure`]: a horizontal slice through the vehicle — occupancy, the potential φ on
//!   the planning domain (log scale), the direction of steepest descent of φ and the chosen
//!   path (the streamline, or a baseline's A* path) — the seed paper's Fig. 2.
//! - [`top_view`]: the flown path over the final map, seen from above (grey level: the share
//!   of a column's observed voxels that are occupied).
//! - [`coverage_curves`]: free coverage against distance flown, one mean curve per planner over
//!   the runs of a bench, with every run faintly behind it.
//! - [`write_ply`]: occupied voxel centres as an ASCII PLY point cloud (MeshLab, CloudCompare,
//!   Open3D); the `.npy` label grid comes from [`crate::io::labels::labels_from_map`].

use std::path::Path;
use std::sync::Once;

use harmonic_core::domain::Label;
use harmonic_core::map::{Occupancy, VoxelIndex, VoxelMap};
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::run::sim::StepView;

static FONTS: Once = Once::new();

/// Registers the embedded font as `sans-serif` (once).
fn fonts() {
    FONTS.call_once(|| {
        // The bytes are a valid TrueType font shipped by the `dejavu` crate.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font("sans-serif", FontStyle::Bold, dejavu::sans::bold());
    });
}

fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// One horizontal layer of the planner's state, captured during a run.
#[derive(Debug, Clone)]
pub struct SliceSnapshot {
    /// Step of the capture.
    pub step: u32,
    /// Planner name.
    pub planner: String,
    /// Layer index (z voxel of the vehicle).
    pub layer: usize,
    /// Grid size in x and y.
    pub nx: usize,
    /// Grid size in y.
    pub ny: usize,
    /// Voxel edge, m.
    pub resolution: f32,
    /// Grid origin x, y, z (m).
    pub origin: [f32; 3],
    /// Per cell: 0 unknown, 1 free, 2 occupied.
    pub occupancy: Vec<u8>,
    /// Per cell: domain label.
    pub labels: Vec<Label>,
    /// Per cell: φ in the domain (NaN outside), when the planner has a potential.
    pub phi: Option<Vec<f32>>,
    /// Per cell: unit direction of steepest descent of φ in the slice plane (zero outside).
    pub descent: Vec<[f32; 2]>,
    /// Waypoints of the plan, map frame.
    pub waypoints: Vec<[f32; 3]>,
    /// Vehicle position and yaw.
    pub vehicle: ([f32; 3], f32),
}

impl SliceSnapshot {
    /// Captures the layer through the vehicle after a full plan; `None` when the step kept its
    /// goal, planned nothing, or the vehicle is outside the grid.
    pub fn capture(view: &StepView<'_>) -> Option<Self> {
        let record = view.record?;
        if record.outcome != "goal" {
            return None;
        }
        let map = view.planner.map();
        let g = *map.geometry();
        let dims = g.dims();
        let at = view.planned_at?;
        let v = g.voxel_at(&at)?;
        let (nx, ny) = (dims.nx(), dims.ny());
        let z = v.z;
        let labels_all = view.planner.labels();
        let psi = view.planner.potential();
        let mut occupancy = Vec::with_capacity(nx * ny);
        let mut labels = Vec::with_capacity(nx * ny);
        let mut phi = psi.map(|_| Vec::with_capacity(nx * ny));
        let mut descent = Vec::with_capacity(nx * ny);
        let in_domain = |i: usize| labels_all.get(i).is_some_and(|l| l.in_domain());
        for y in 0..ny {
            for x in 0..nx {
                let c = VoxelIndex::new(x as u16, y as u16, z);
                let i = dims.linear(c);
                occupancy.push(match map.occupancy(i) {
                    Occupancy::Unknown => 0,
                    Occupancy::Free => 1,
                    _ => 2,
                });
                labels.push(labels_all.get(i).copied().unwrap_or(Label::Outside));
                let mut d = [0.0f32; 2];
                if let (Some(psi), Some(phi)) = (psi, phi.as_mut()) {
                    phi.push(if in_domain(i) { 1.0 - psi[i] } else { f32::NAN });
                    if in_domain(i) {
                        // ψ = 1 − φ rises where φ falls: its central difference is the descent.
                        let side = |dx: i32, dy: i32| {
                            dims.offset(c, [dx, dy, 0])
                                .map(|n| dims.linear(n))
                                .filter(|&n| in_domain(n))
                                .map_or(psi[i], |n| psi[n])
                        };
                        let gx = side(1, 0) - side(-1, 0);
                        let gy = side(0, 1) - side(0, -1);
                        let n = (gx * gx + gy * gy).sqrt();
                        if n > 0.0 && n.is_finite() {
                            d = [gx / n, gy / n];
                        }
                    }
                }
                descent.push(d);
            }
        }
        Some(Self {
            step: record.step,
            planner: view.planner.kind().name().to_string(),
            layer: usize::from(z),
            nx,
            ny,
            resolution: g.resolution(),
            origin: g.origin().coords.into(),
            occupancy,
            labels,
            phi,
            descent,
            waypoints: view.planner.waypoints().iter().map(|p| p.coords.into()).collect(),
            vehicle: (at.coords.into(), record.yaw),
        })
    }
}

/// A perceptually ordered colour map (viridis, five stops, linear in between), `t` in 0..=1.
fn viridis(t: f32) -> RGBColor {
    const STOPS: [(f32, f32, f32); 5] = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let t = t.clamp(0.0, 1.0) * 4.0;
    let k = (t.floor() as usize).min(3);
    let f = t - k as f32;
    let (a, b) = (STOPS[k], STOPS[k + 1]);
    let mix = |x: f32, y: f32| (x + (y - x) * f).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// Writes the slice figure of `snap` to `path` (PNG).
pub fn slice_figure(snap: &SliceSnapshot, scenario: &str, path: &Path) -> Result<(), String> {
    fonts();
    let r = snap.resolution;
    let (ox, oy) = (snap.origin[0], snap.origin[1]);
    let (w_m, h_m) = (snap.nx as f32 * r, snap.ny as f32 * r);
    let px_per_m = (900.0 / w_m.max(h_m)).clamp(40.0, 120.0);
    let size = ((w_m * px_per_m) as u32 + 190, (h_m * px_per_m) as u32 + 90);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let z = snap.origin[2] + (snap.layer as f32 + 0.5) * r;
    let title = format!(
        "{scenario}, {}, step {}: slice z = {z:.2} m",
        snap.planner, snap.step
    );
    let (plot, legend) = root.split_horizontally(size.0 - 150);
    let mut chart = ChartBuilder::on(&plot)
        .caption(title, ("sans-serif", 18))
        .margin(8)
        .x_label_area_size(30)
        .y_label_area_size(40)
        .build_cartesian_2d(ox..ox + w_m, oy..oy + h_m)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("x (m)")
        .y_desc("y (m)")
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(err)?;
    // log10 φ range over the domain, for the colour scale.
    let (mut lo, hi) = (f32::INFINITY, 0.0f32);
    if let Some(phi) = &snap.phi {
        for &p in phi.iter().filter(|p| p.is_finite() && **p > 0.0) {
            lo = lo.min(p.log10());
        }
    }
    let lo = if lo.is_finite() {
        lo.max(-12.0).min(hi - 1.0)
    } else {
        -6.0
    };
    let cell = |x: usize, y: usize| {
        let x0 = ox + x as f32 * r;
        let y0 = oy + y as f32 * r;
        [(x0, y0), (x0 + r, y0 + r)]
    };
    let mut rects = Vec::with_capacity(snap.nx * snap.ny);
    for y in 0..snap.ny {
        for x in 0..snap.nx {
            let i = y * snap.nx + x;
            let colour = match (snap.labels[i], snap.occupancy[i]) {
                (Label::Frontier, _) => RGBColor(230, 60, 50),
                (Label::Source, _) => RGBColor(255, 255, 255),
                (l, _) if l.in_domain() => match &snap.phi {
                    Some(phi) if phi[i] > 0.0 => viridis((phi[i].log10() - lo) / (hi - lo)),
                    Some(_) => viridis(0.0),
                    None => RGBColor(190, 230, 190),
                },
                (_, 0) => RGBColor(205, 205, 215),
                (_, 2) => RGBColor(20, 20, 20),
                _ => RGBColor(252, 252, 252),
            };
            rects.push(Rectangle::new(cell(x, y), colour.filled()));
        }
    }
    chart.draw_series(rects).map_err(err)?;
    // Descent directions on every third cell.
    let step = 3;
    let mut arrows = Vec::new();
    for y in (1..snap.ny).step_by(step) {
        for x in (1..snap.nx).step_by(step) {
            let i = y * snap.nx + x;
            let d = snap.descent[i];
            if d == [0.0, 0.0] || snap.labels[i] == Label::Frontier {
                continue;
            }
            let c = (ox + (x as f32 + 0.5) * r, oy + (y as f32 + 0.5) * r);
            let len = 1.2 * r;
            let tip = (c.0 + d[0] * len, c.1 + d[1] * len);
            let back = (-d[0] * 0.45 * r, -d[1] * 0.45 * r);
            let side = (-d[1] * 0.3 * r, d[0] * 0.3 * r);
            arrows.push(PathElement::new(vec![c, tip], WHITE.stroke_width(1)));
            arrows.push(PathElement::new(
                vec![
                    (tip.0 + back.0 + side.0, tip.1 + back.1 + side.1),
                    tip,
                    (tip.0 + back.0 - side.0, tip.1 + back.1 - side.1),
                ],
                WHITE.stroke_width(1),
            ));
        }
    }
    chart.draw_series(arrows).map_err(err)?;
    let path_pts: Vec<(f32, f32)> = snap.waypoints.iter().map(|p| (p[0], p[1])).collect();
    chart
        .draw_series(LineSeries::new(
            path_pts.clone(),
            RGBColor(255, 140, 0).stroke_width(3),
        ))
        .map_err(err)?;
    if let Some(end) = path_pts.last() {
        chart
            .draw_series([Circle::new(*end, 5, RGBColor(255, 140, 0).filled())])
            .map_err(err)?;
    }
    let (v, yaw) = snap.vehicle;
    chart
        .draw_series([Circle::new((v[0], v[1]), 6, BLUE.filled())])
        .map_err(err)?;
    chart
        .draw_series([PathElement::new(
            vec![(v[0], v[1]), (v[0] + 0.4 * yaw.cos(), v[1] + 0.4 * yaw.sin())],
            BLUE.stroke_width(3),
        )])
        .map_err(err)?;
    // Legend: colour bar and keys.
    let keys: [(&str, RGBColor); 6] = [
        ("unknown", RGBColor(205, 205, 215)),
        ("occupied", RGBColor(20, 20, 20)),
        ("free, not in domain", RGBColor(240, 240, 240)),
        ("frontier (phi = 0)", RGBColor(230, 60, 50)),
        ("path", RGBColor(255, 140, 0)),
        ("vehicle", BLUE),
    ];
    for (k, (name, c)) in keys.iter().enumerate() {
        let y = 40 + 22 * k as i32;
        legend
            .draw(&Rectangle::new([(8, y), (24, y + 14)], c.filled()))
            .map_err(err)?;
        legend
            .draw(&Text::new(name.to_string(), (30, y), ("sans-serif", 12)))
            .map_err(err)?;
    }
    if snap.phi.is_some() {
        let top = 40 + 22 * keys.len() as i32 + 20;
        legend
            .draw(&Text::new("log10 phi", (8, top), ("sans-serif", 12)))
            .map_err(err)?;
        let h = 200;
        for k in 0..h {
            let t = 1.0 - k as f32 / h as f32;
            legend
                .draw(&Rectangle::new(
                    [(8, top + 18 + k), (28, top + 19 + k)],
                    viridis(t).filled(),
                ))
                .map_err(err)?;
        }
        legend
            .draw(&Text::new(format!("{hi:.0}"), (34, top + 14), ("sans-serif", 12)))
            .map_err(err)?;
        legend
            .draw(&Text::new(
                format!("{lo:.1}"),
                (34, top + 10 + h),
                ("sans-serif", 12),
            ))
            .map_err(err)?;
        legend
            .draw(&Text::new(
                "arrows: -grad phi",
                (8, top + 40 + h),
                ("sans-serif", 12),
            ))
            .map_err(err)?;
    }
    root.present().map_err(err)?;
    Ok(())
}

/// Writes the flown path over the final map, seen from above, to `path` (PNG).
pub fn top_view(map: &VoxelMap<'_>, trajectory: &[[f32; 3]], title: &str, path: &Path) -> Result<(), String> {
    let g = *map.geometry();
    let dims = g.dims();
    let state = |x: usize, y: usize, z: usize| match map
        .occupancy(dims.linear(VoxelIndex::new(x as u16, y as u16, z as u16)))
    {
        Occupancy::Unknown => 0u8,
        Occupancy::Free => 1,
        _ => 2,
    };
    draw_top_view(
        [dims.nx(), dims.ny(), dims.nz()],
        g.origin().coords.into(),
        g.resolution(),
        state,
        trajectory,
        title,
        path,
    )
}

/// [`top_view`] from a label grid (0 unknown, 1 free, 2 occupied, as `map.npy` holds it) whose
/// voxel (0,0,0) starts at `origin`.
pub fn top_view_labels(
    grid: &crate::io::npy::Array3<u8>,
    origin: [f32; 3],
    resolution: f32,
    trajectory: &[[f32; 3]],
    title: &str,
    path: &Path,
) -> Result<(), String> {
    let state = |x: usize, y: usize, z: usize| grid.get(x, y, z).copied().unwrap_or(0);
    draw_top_view(grid.shape, origin, resolution, state, trajectory, title, path)
}

fn draw_top_view(
    shape: [usize; 3],
    origin: [f32; 3],
    r: f32,
    state: impl Fn(usize, usize, usize) -> u8,
    trajectory: &[[f32; 3]],
    title: &str,
    path: &Path,
) -> Result<(), String> {
    fonts();
    let [nx, ny, nz] = shape;
    let (ox, oy) = (origin[0], origin[1]);
    let (w_m, h_m) = (nx as f32 * r, ny as f32 * r);
    let px_per_m = (900.0 / w_m.max(h_m)).clamp(40.0, 120.0);
    let size = ((w_m * px_per_m) as u32 + 70, (h_m * px_per_m) as u32 + 80);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(8)
        .x_label_area_size(30)
        .y_label_area_size(40)
        .build_cartesian_2d(ox..ox + w_m, oy..oy + h_m)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("x (m)")
        .y_desc("y (m)")
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(err)?;
    let mut rects = Vec::with_capacity(nx * ny);
    for y in 0..ny {
        for x in 0..nx {
            let (mut observed, mut occupied) = (0u32, 0u32);
            for z in 0..nz {
                match state(x, y, z) {
                    0 => {}
                    1 => observed += 1,
                    _ => {
                        observed += 1;
                        occupied += 1;
                    }
                }
            }
            let colour = if observed == 0 {
                RGBColor(200, 210, 230)
            } else {
                let f = occupied as f32 / observed as f32;
                let v = (250.0 - 235.0 * f) as u8;
                RGBColor(v, v, v)
            };
            let (x0, y0) = (ox + x as f32 * r, oy + y as f32 * r);
            rects.push(Rectangle::new([(x0, y0), (x0 + r, y0 + r)], colour.filled()));
        }
    }
    chart.draw_series(rects).map_err(err)?;
    let n = trajectory.len().max(2) as f32;
    chart
        .draw_series(trajectory.windows(2).enumerate().map(|(k, w)| {
            let t = k as f32 / n;
            let c = RGBColor((60.0 + 195.0 * t) as u8, 40, (220.0 - 180.0 * t) as u8);
            PathElement::new(vec![(w[0][0], w[0][1]), (w[1][0], w[1][1])], c.stroke_width(2))
        }))
        .map_err(err)?;
    if let (Some(a), Some(b)) = (trajectory.first(), trajectory.last()) {
        chart
            .draw_series([
                Circle::new((a[0], a[1]), 6, RGBColor(60, 40, 220).filled()),
                Circle::new((b[0], b[1]), 6, RGBColor(255, 40, 40).filled()),
            ])
            .map_err(err)?;
    }
    root.present().map_err(err)?;
    Ok(())
}

/// Colour of a planner's curves.
fn planner_colour(name: &str) -> RGBColor {
    match name {
        "random-frontier" => RGBColor(150, 150, 150),
        "closest-frontier" => RGBColor(31, 119, 180),
        "info-gain" => RGBColor(44, 160, 44),
        "weighted-info-gain" => RGBColor(148, 103, 189),
        "harmonic-gs" => RGBColor(255, 127, 14),
        "harmonic-thesis" => RGBColor(140, 86, 75),
        "harmonic" => RGBColor(214, 39, 40),
        _ => BLACK,
    }
}

/// Coverage of a run at distance `d`: the coverage of its last step within `d` (its final
/// coverage once it has ended).
fn coverage_at(points: &[(f64, f64)], d: f64) -> f64 {
    let k = points.partition_point(|p| p.0 <= d);
    if k == 0 {
        0.0
    } else {
        points[k - 1].1
    }
}

/// Coverage against distance flown over one run: `(path_length_m, coverage_free)` per step
/// (a bench's `curves.csv`, read back by `batch::read_curves`).
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// Scenario name.
    pub scenario: String,
    /// Planner name.
    pub planner: String,
    /// Seed.
    pub seed: u64,
    /// `(metres flown, free coverage)` after every step.
    pub points: Vec<(f64, f64)>,
}

/// Writes free coverage against distance flown for every planner of one scenario (mean over
/// runs, bold; each run faint) to `path` (PNG).
pub fn coverage_curves(curves: &[Curve], scenario: &str, path: &Path) -> Result<(), String> {
    fonts();
    let mine: Vec<&Curve> = curves.iter().filter(|c| c.scenario == scenario).collect();
    if mine.is_empty() {
        return Err(format!("no curves for scenario `{scenario}`"));
    }
    let mut planners: Vec<&str> = mine.iter().map(|c| c.planner.as_str()).collect();
    planners.sort_by_key(|p| {
        crate::planners::PlannerKind::ALL
            .iter()
            .position(|k| k.name() == *p)
            .unwrap_or(usize::MAX)
    });
    planners.dedup();
    let max_d = mine
        .iter()
        .filter_map(|c| c.points.last().map(|p| p.0))
        .fold(1.0f64, f64::max);
    let root = BitMapBackend::new(path, (900, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{scenario}: free coverage against distance flown"),
            ("sans-serif", 18),
        )
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(0.0..max_d * 1.02, 0.0..100.0)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("distance flown (m)")
        .y_desc("free coverage (%)")
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(err)?;
    let grid: Vec<f64> = (0..=300).map(|k| max_d * f64::from(k) / 300.0).collect();
    for p in &planners {
        let colour = planner_colour(p);
        let runs: Vec<&&Curve> = mine.iter().filter(|c| c.planner == *p).collect();
        for c in &runs {
            chart
                .draw_series(LineSeries::new(
                    c.points.iter().map(|(d, v)| (*d, 100.0 * v)),
                    colour.mix(0.18).stroke_width(1),
                ))
                .map_err(err)?;
        }
        let mean: Vec<(f64, f64)> = grid
            .iter()
            .map(|&d| {
                let s: f64 = runs.iter().map(|c| coverage_at(&c.points, d)).sum();
                (d, 100.0 * s / runs.len() as f64)
            })
            .collect();
        chart
            .draw_series(LineSeries::new(mean, colour.stroke_width(3)))
            .map_err(err)?
            .label(format!("{p} ({} runs)", runs.len()))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(3)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

/// The occupied voxel centres of `map` as an ASCII PLY point cloud.
pub fn ply(map: &VoxelMap<'_>) -> String {
    let g = *map.geometry();
    let dims = g.dims();
    let points: Vec<[f32; 3]> = (0..dims.len())
        .filter(|&i| map.occupancy(i) == Occupancy::Occupied)
        .map(|i| g.center(dims.voxel(i)).coords.into())
        .collect();
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment harmonic-sim: occupied voxel centres, map frame (m), voxel {} m\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        g.resolution(),
        points.len()
    );
    for p in points {
        s.push_str(&format!("{} {} {}\n", p[0], p[1], p[2]));
    }
    s
}

/// Writes [`ply`] to `path`.
pub fn write_ply(map: &VoxelMap<'_>, path: &Path) -> Result<(), String> {
    std::fs::write(path, ply(map)).map_err(|e| format!("{}: {e}", path.display()))
}

/// Writes the map's `.npy` label grid (0 unknown, 1 free, 2 occupied) to `path`.
pub fn write_labels(map: &VoxelMap<'_>, path: &Path) -> Result<(), String> {
    let grid = crate::io::labels::labels_from_map(map);
    std::fs::write(path, crate::io::npy::write_u8(&grid)).map_err(|e| format!("{}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::map::{Dims, LogOddsParams, MapGeometry};
    use nalgebra::Point3;

    #[test]
    fn ply_lists_occupied_centres() {
        let g = MapGeometry::new(Dims::new(3, 2, 2).unwrap(), Point3::new(1.0, 0.0, 0.0), 0.5).unwrap();
        let (mut lo, mut st) = (vec![0i8; 12], vec![0u32; 1]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo, &mut st).unwrap();
        map.apply_hit(g.dims().linear(VoxelIndex::new(2, 1, 0)));
        map.apply_miss(0);
        let text = ply(&map);
        assert!(text.contains("element vertex 1\n"), "{text}");
        assert!(text.trim_end().ends_with("2.25 0.75 0.25"), "{text}");
    }

    #[test]
    fn coverage_curve_steps_and_holds() {
        let pts = [(0.0, 0.1), (1.0, 0.5), (2.5, 0.9)];
        assert_eq!(coverage_at(&pts, 0.5), 0.1);
        assert_eq!(coverage_at(&pts, 1.0), 0.5);
        assert_eq!(coverage_at(&pts, 10.0), 0.9);
        assert_eq!(coverage_at(&[], 1.0), 0.0);
    }

    #[test]
    fn curves_render_to_png_without_system_fonts() {
        let dir = std::env::temp_dir().join(format!("hs-fig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = |planner: &str, seed| Curve {
            scenario: "s1".into(),
            planner: planner.into(),
            seed,
            points: vec![(0.0, 0.1), (5.0, 0.6), (9.0, 0.99)],
        };
        let path = dir.join("coverage_s1.png");
        coverage_curves(&[c("harmonic", 1), c("closest-frontier", 1)], "s1", &path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        assert!(coverage_curves(&[c("harmonic", 1)], "s2", &path).is_err());
        let _ = std::fs::remove_dir_all(dir);
    }
}
